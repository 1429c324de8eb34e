import h5py, json, sys, os, hashlib, numpy as np
d = sys.argv[1]
m = json.load(open(os.path.join(d, "manifest.json")))
def bpm(mid):
    g, k = mid[:3], int(mid[3:])
    return 110 + 5 * k if g == "mHO" else 80 + 10 * k
mel_by_music = {}
n_seq = 0
for e in m["shards"]:
    p = os.path.join(d, e["file"])
    assert hashlib.sha256(open(p, "rb").read()).hexdigest() == e["sha256"], e["file"]
    f = h5py.File(p, "r")
    assert f.attrs["format"] == "choreod-prep-shard" and f.attrs["split"] == e["split"], dict(f.attrs)
    assert int(f.attrs["sequences"]) == e["sequences"] == len(f.keys())
    frames = 0
    for name in f:
        g = f[name]
        n = g["joints30"].shape[0]
        assert g["joints30"].shape == (n, 24, 3) and g["joints30"].dtype == np.float32
        assert g["joints60"].shape[1:] == (24, 3) and n == (g["joints60"].shape[0] + 1) // 2
        assert np.array_equal(g["joints30"][:], g["joints60"][::2]), name
        assert g["mel"].shape == (n, 80) and g["onset"].shape == (n,)
        b = g["beats"][:]
        assert b.dtype == np.int32 and len(b) > 0 and b.min() >= 0 and b.max() < n and np.all(np.diff(b) > 0)
        assert g.attrs["music_id"] == name.split("_")[4] and g.attrs["genre"] == name.split("_")[0]
        assert g.attrs["bpm"] == bpm(g.attrs["music_id"]), (name, g.attrs["bpm"])
        assert n >= 150 and np.isfinite(g["mel"][:]).all() and np.isfinite(g["joints60"][:]).all()
        mel_by_music.setdefault(g.attrs["music_id"], []).append(g["mel"][:])
        frames += n
        n_seq += 1
    assert frames == e["frames"]
# Same music, same times: every sequence's mel is a prefix of the same aligned track.
shared = 0
for mid, mels in mel_by_music.items():
    for a in mels[1:]:
        k = min(len(a), len(mels[0]))
        assert np.array_equal(a[:k], mels[0][:k]), mid
        shared += 1
assert shared > 0
print(n_seq)
