# Captured mel against the offline mel of the same samples, aligned by the best lag of the
# frame-energy envelopes.
import h5py, json, sys, numpy as np
with h5py.File(sys.argv[1], "r") as f:
    cap = f["audio/mel"][:].astype(np.float64)
ref = np.load(sys.argv[2]).T.astype(np.float64)
floor = ref.max() - 80.0
cap = np.maximum(cap, floor)
# The feed starts before choreod listens, so the capture starts somewhere in the song:
# cap[i] ~ ref[i + k] for the best k.
n = len(cap) - 8
env_c, env_r = cap[:n].mean(1), ref.mean(1)
best = max(range(0, len(ref) - n), key=lambda k: np.corrcoef(env_c, env_r[k:k + n])[0, 1])
a, b = cap[:n], ref[best:best + n]
diff = np.abs(a - b)
loud = b > floor + 20
print(json.dumps({"lag": best, "frames": n, "median_db": float(np.median(diff[loud])),
                  "p90_db": float(np.percentile(diff[loud], 90)),
                  "corr": float(np.corrcoef(a.ravel(), b.ravel())[0, 1])}))
