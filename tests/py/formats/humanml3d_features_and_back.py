import sys, numpy as np
f = np.load(sys.argv[1]); j = np.load(sys.argv[2]); f2 = np.load(sys.argv[3])
assert f.shape == (239, 263) and f.dtype == np.float32
assert j.shape == (239, 22, 3)
assert set(np.unique(f[:, 259:])) <= {0.0, 1.0}
assert f2.shape == (238, 263)
# Re-extracting from recovered joints keeps the root height and ric within 1 mm.
assert np.abs(f2[:, 3:67] - f[:-1, 3:67]).max() < 1e-3, np.abs(f2[:, 3:67] - f[:-1, 3:67]).max()
print("ok")
