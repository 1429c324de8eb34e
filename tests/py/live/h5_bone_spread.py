# How much each bone's length varies over a motion file's frames (max − min, metres, the
# largest over the bones); argv: file, the skeleton's parents as JSON.
import h5py, json, sys, numpy as np
parents = json.loads(sys.argv[2])
with h5py.File(sys.argv[1], "r") as f:
    j = f["motion/joints"][:].astype(np.float64)
spread = 0.0
for k, p in enumerate(parents):
    if p >= 0:
        lengths = np.linalg.norm(j[:, k] - j[:, p], axis=1)
        spread = max(spread, float(lengths.max() - lengths.min()))
print(json.dumps({"frames": len(j), "spread_m": spread, "extent_m": float(np.abs(j).max())}))
