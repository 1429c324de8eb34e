import sys, os, json, hashlib, h5py, numpy as np
d = sys.argv[1]
with h5py.File(os.path.join(d, "elsewhere.h5"), "w") as f:
    f["sum"] = np.full(263, 1e9)
shard = os.path.join(d, "train-00000.h5")
with h5py.File(shard, "a") as f:
    del f["_stats/sum"]
    f["_stats/sum"] = h5py.ExternalLink("elsewhere.h5", "/sum")
m = json.load(open(os.path.join(d, "manifest.json")))
for e in m["shards"]:
    if e["file"] == "train-00000.h5":
        e["sha256"] = hashlib.sha256(open(shard, "rb").read()).hexdigest()
        e["bytes"] = os.path.getsize(shard)
json.dump(m, open(os.path.join(d, "manifest.json"), "w"))
print("ok")
