import sys, h5py, numpy as np
f = h5py.File(sys.argv[1], "r")
assert f.attrs["format"] == "choreod-motion" and int(f.attrs["format_version"]) == 2
j = f["motion/joints"][:]
assert j.shape == (720, 24, 3) and j.dtype == np.float32
assert f["motion"].attrs["skeleton"] == "smpl24" and float(f["motion"].attrs["fps"]) == 60.0
a = np.load(sys.argv[2]); b = np.load(sys.argv[3]); r = np.load(sys.argv[4])
assert r.shape == j.shape and np.abs(r - j).max() < 1e-4, np.abs(r - j).max()
assert np.array_equal(a, j)
# BVH text keeps 6 decimals; rotations recovered from positions reproduce them to 1e-4 m.
assert b.shape == j.shape and np.abs(b - j).max() < 1e-4, np.abs(b - j).max()
print("ok")
