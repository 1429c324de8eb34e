import sys, numpy as np
got = np.load(sys.argv[1]); want = np.load(sys.argv[2])["features"]
assert got.dtype == np.float32 and got.shape == want.shape, (got.dtype, got.shape, want.shape)
rng = want[:, :33].max(0) - want[:, :33].min(0)
err = (np.abs(got[:, :33] - want[:, :33]).max(0) / np.maximum(rng, 1e-12)).max()
assert err <= 1e-3, f"continuous columns: {err:.2e} of range"
assert (got[:, 33:] == want[:, 33:]).all(), "one-hot columns differ"
print(f"ok continuous columns within {err:.2e} of their range, one-hot identical")
