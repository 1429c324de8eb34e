import sys, os, shutil, h5py, numpy as np
base, d = sys.argv[1], sys.argv[2]
secret = os.path.join(d, "secret.bin")
with open(secret, "wb") as f:
    f.write(np.full((1, 24, 3), 1234.5, np.float32).tobytes())
with h5py.File(os.path.join(d, "other.h5"), "w") as f:
    f["j"] = np.full((1, 24, 3), 1234.5, np.float32)
for name in ["storage", "extlink", "softlink", "virtual"]:
    p = os.path.join(d, name + ".h5")
    shutil.copy(base, p)
    with h5py.File(p, "a") as f:
        m = f["motion"]
        del m["joints"]
        if name == "storage":
            m.create_dataset("joints", shape=(1, 24, 3), dtype=np.float32, external=[(secret, 0, 288)])
        elif name == "extlink":
            m["joints"] = h5py.ExternalLink("other.h5", "/j")
        elif name == "softlink":
            f["elsewhere"] = np.zeros((1, 24, 3), np.float32)
            m["joints"] = h5py.SoftLink("/elsewhere")
        else:
            layout = h5py.VirtualLayout(shape=(1, 24, 3), dtype=np.float32)
            layout[:] = h5py.VirtualSource("other.h5", "j", shape=(1, 24, 3))
            m.create_virtual_dataset("joints", layout)
print("ok")
