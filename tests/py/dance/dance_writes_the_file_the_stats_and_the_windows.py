import sys, h5py, numpy as np
f = h5py.File(sys.argv[1], "r")
assert int(f.attrs["format_version"]) == 2
j = f["motion/joints"]
assert j.shape == (int(sys.argv[3]), 24, 3) and np.isfinite(j[...]).all(), j.shape
p = f["provenance"].attrs
assert p["sampler"] == "dpmsolver++" and int(p["steps"]) == 6, dict(p)
assert float(p["eta"]) == 0.0 and int(p["chunk_windows"]) == 32 and p["init_noise_sha256"] == ""
assert float(p["guidance"]) == 1.0 and int(p["seed"]) == 0
w = np.load(sys.argv[2])
assert w.dtype == np.float32 and w.shape == (int(sys.argv[4]), 150, 72), w.shape
print("ok")
