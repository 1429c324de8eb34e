import sys, os, hashlib, h5py
p = h5py.File(sys.argv[1], "r")["provenance"].attrs
src = sys.argv[2]
assert p["source_name"] == os.path.basename(src), p["source_name"]
assert p["source_sha256"] == hashlib.sha256(open(src, "rb").read()).hexdigest()
assert p["model_name"] == "choreod convert", p["model_name"]
assert p["sampler"] == "AIST++ motion → motion file (choreod convert --to features)", p["sampler"]
assert p["started_utc"].endswith("Z") and p["finished_utc"] >= p["started_utc"]
print("ok")
