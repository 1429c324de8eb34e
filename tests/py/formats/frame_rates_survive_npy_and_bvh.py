import sys, h5py
assert float(h5py.File(sys.argv[1], "r")["motion"].attrs["fps"]) == 60.0
print("ok")
