import sys, h5py, numpy as np
with h5py.File(sys.argv[1], "r") as f:
    ours = f["motion/features"][:]
    p = f["provenance"].attrs
    assert p["style_mode"] == sys.argv[3] and p["style_name"] == "style.npy", dict(p)
theirs = np.load(sys.argv[2])
# float32 state here, float64 there, over <= 30 network calls on outputs of scale ~3:
# 1e-4 of the output's scale (the bound).
rel = np.abs(ours - theirs).max() / np.abs(theirs).max()
assert ours.shape == theirs.shape and rel < 1e-4, rel
print(f"ok {sys.argv[3]}: relative difference {rel:.1e}")
