import sys, h5py, numpy as np
a = h5py.File(sys.argv[1], "r")["motion/features"][:]
b = h5py.File(sys.argv[2], "r")["motion/features"][:]
p = h5py.File(sys.argv[2], "r")["provenance"].attrs
assert p["style_name"] == "style-vector.npy", dict(p)
# float32 statistics in the graph vs float64 here, on metre-scale values: 1e-5 m.
err = np.abs(a - b).max()
assert err < 1e-5, err
print(f"ok embedding = style motion within {err:.1e}")
