import sys, h5py, hashlib, numpy as np
with h5py.File(sys.argv[1], "r") as f:
    j = f["motion/joints"][:]
    x = f["motion/features"][:]
    p = f["provenance"].attrs
    assert f["motion"].attrs["skeleton"] == "t2m22" and float(f["motion"].attrs["fps"]) == 20.0
    assert f["motion/features"].attrs["representation"] == "humanml3d263"
    assert not f["motion/features"].attrs["normalized"]
    frames = int(sys.argv[3])
    assert j.shape == (frames, 22, 3) and x.shape == (frames, 263), (j.shape, x.shape)
    assert np.isfinite(j).all() and np.isfinite(x).all()
    sha = lambda q: hashlib.sha256(open(q, "rb").read()).hexdigest()
    assert p["source_sha256"] == sha(sys.argv[2]) and p["style_sha256"] == sha(sys.argv[4])
    assert p["model_name"] == "style-gaussian" and p["style_mode"] == "transfer"
    assert p["sampler"] == "ddim" and int(p["steps"]) == 50
print("ok", sys.argv[2].rsplit("/", 1)[-1], j.shape)
