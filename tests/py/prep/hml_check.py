import h5py, json, sys, os, numpy as np
d = sys.argv[1]
m = json.load(open(os.path.join(d, "manifest.json")))
feats, names, byname = [], set(), {}
for e in m["shards"]:
    f = h5py.File(os.path.join(d, e["file"]), "r")
    for name in f:
        if name == "_stats":
            continue
        g = f[name]
        x = g["features"][:]
        assert x.dtype == np.float32 and x.shape[1] == 263 and g["joints"].shape == (x.shape[0] + 1, 22, 3)
        caps = [c.decode() if isinstance(c, bytes) else c for c in g["captions"][:]]
        assert g["spans"].shape == (len(caps), 2) and g["tokens"].shape == (len(caps),)
        if name.startswith("M"):
            assert g.attrs["mirrored"] == 1 and g.attrs["source"] == name[1:]
            if caps:
                assert caps[0] == "a person raises the right hand", caps
        elif caps:
            assert caps[0] == "a person raises the left hand", caps
        feats.append(x.astype(np.float64))
        names.add(name)
        byname[name] = x
# A mirrored copy turns the other way: root rotation velocity (dim 0) flips sign. Not exactly:
# both are retargeted to HumanML3D's target skeleton, whose left and right bones differ by up to
# 7 %, so the mirror's facing direction (from hips and shoulders) is off by a few degrees (the
# sum reached 14 % of the peak |dim 0| here). An unmirrored copy would give x + M = 2x and
# x - M = 0, so the sum staying under a quarter of the difference still proves the flip.
pairs = 0
for name, x in byname.items():
    if "M" + name in byname:
        mx = byname["M" + name][:, 0]
        err, flip = np.abs(x[:, 0] + mx).max(), np.abs(x[:, 0] - mx).max()
        assert err < 0.25 * flip, (name, err, flip)
        pairs += 1
assert pairs == 41, pairs
allf = np.concatenate(feats)
mean = allf.mean(0)
std = allf.std(0)
for a0, b0 in [(0, 1), (1, 3), (3, 4), (4, 67), (67, 193), (193, 259), (259, 263)]:
    std[a0:b0] = std[a0:b0].mean()
M = np.load(os.path.join(d, "Mean.npy")); S = np.load(os.path.join(d, "Std.npy"))
assert M.shape == (263,) and S.shape == (263,) and M.dtype == np.float32
# f64 sums in both; only the final f32 rounding differs: 1e-5 relative + 1e-6 absolute.
assert np.allclose(M, mean, rtol=1e-5, atol=1e-6), np.abs(M - mean).max()
assert np.allclose(S, std, rtol=1e-5, atol=1e-6), np.abs(S - std).max()
assert m["mean_std"]["frames"] == len(allf)
print(len(names))
