"""Every sequence's `fact35` against `choreod features` of its music (argv: shard dir, features dir holding `<music id>.npy`, the librosa release): same frames as `joints30`, float32, bit-identical to the verb's first T rows; the shard names the set."""
import h5py, json, sys, os, numpy as np
d, feats, release = sys.argv[1:4]
m = json.load(open(os.path.join(d, "manifest.json")))
assert m["parameters"]["music_features"]["set"] == "fact35", m["parameters"]
n = 0
for e in m["shards"]:
    f = h5py.File(os.path.join(d, e["file"]), "r")
    assert f.attrs["music_features"] == "fact35" and f.attrs["fact35_librosa"] == release, dict(f.attrs)
    for name in f:
        g = f[name]
        x = g["fact35"][:]
        want = np.load(os.path.join(feats, g.attrs["music_id"] + ".npy"))
        assert x.dtype == np.float32 and x.shape == (g["joints30"].shape[0], 35), (name, x.shape)
        assert np.array_equal(x, want[: len(x)]), (name, np.abs(x - want[: len(x)]).max())
        n += 1
print(f"ok {n} sequences")
