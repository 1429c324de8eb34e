import sys, os, shutil, h5py, numpy as np
base, d = sys.argv[1], sys.argv[2]
for name, opts in [("unwritten", {}), ("unwritten_gzip", {"chunks": (64, 24, 3), "compression": "gzip"})]:
    p = os.path.join(d, name + ".h5")
    shutil.copy(base, p)
    with h5py.File(p, "a") as f:
        del f["motion/joints"]
        f["motion"].create_dataset("joints", shape=(13_500_000, 24, 3), dtype=np.float32, **opts)
    assert os.path.getsize(p) < 100_000, os.path.getsize(p)
print("ok")
