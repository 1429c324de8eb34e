import sys, h5py, hashlib, numpy as np
a, b = (h5py.File(p, "r") for p in sys.argv[1:3])
assert np.array_equal(a["motion/joints"][...], b["motion/joints"][...])
p = a["provenance"].attrs
assert p["init_noise_sha256"] == hashlib.sha256(open(sys.argv[3], "rb").read()).hexdigest()
assert int(p["chunk_windows"]) == 4 and p["sampler"] == "ddim" and int(p["seed"]) == 1
print("ok")
