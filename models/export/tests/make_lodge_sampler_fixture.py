"""Reference LODGE run of the tiny package for models/tests/lodge.rs (not run in CI).

Runs models/packages/lodge-tiny-random's four ONNX files with onnxruntime and the two-stage
loop in numpy, written from the official code's facts (LODGE a898e59: infer_lodge.py:198-299,
Local_Module.py:158-224, diffusion.py:82-86, 262-294, 491-545, 892-1090, concat_res.py) and
pytorch3d 0.7.5's rotation formulas — not from choreod's Rust. Deterministic inputs (features and
every noise draw) come from a splitmix64 generator that the Rust test reimplements, so the
fixture holds outputs only. DDIM eta 0, the package's 50 timesteps, genre 3, both modes:

- official: T = 1300 frames -> 5 Local windows (tail of 20 dropped), 2 Global windows, the
  second one partial (flag 1): the wrong-music and partial-keyframe paths;
- fixed: T = 600 frames -> 3 Local windows (tail danced), 1 Global window on padded music.

Run: python models/export/tests/make_lodge_sampler_fixture.py  (numpy, onnxruntime)
Writes models/tests/fixtures/lodge/sampler.npz.
"""
import pathlib
import tomllib

import numpy as np
import onnxruntime as ort

ROOT = pathlib.Path(__file__).resolve().parents[3]
PKG = ROOT / "models/packages/lodge-tiny-random"
OUT = ROOT / "models/tests/fixtures/lodge/sampler.npz"
F = 139
M64 = (1 << 64) - 1


def splitmix_u64(seed, count):
    """splitmix64 outputs 1..=count of the stream `seed` (Vigna's constants)."""
    with np.errstate(over="ignore"):
        z = np.uint64(seed) + np.arange(1, count + 1, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def normals(seed, shape):
    """Box-Muller of pairs of splitmix64 uniforms, float32."""
    n = int(np.prod(shape))
    z = splitmix_u64(seed, 2 * n)
    u1 = ((z[0::2] >> np.uint64(11)).astype(np.float64) + 1.0) * 2.0**-53
    u2 = (z[1::2] >> np.uint64(11)).astype(np.float64) * 2.0**-53
    return (np.sqrt(-2.0 * np.log(u1)) * np.cos(2.0 * np.pi * u2)).astype(np.float32).reshape(shape)


def features(seed, frames):
    """Uniform -1..1 in columns 0..33, a peak every 10 frames and a beat every 15."""
    z = splitmix_u64(seed, frames * 35)
    f = ((z >> np.uint64(11)).astype(np.float64) * 2.0**-53 * 2.0 - 1.0).astype(np.float32)
    f = f.reshape(frames, 35)
    f[:, 33] = (np.arange(frames) % 10 == 0)
    f[:, 34] = (np.arange(frames) % 15 == 0)
    return f


# pytorch3d 0.7.5 rotation_conversions.py, float64 inside, float32 out.
def rot6d_to_mat(d6):
    a1, a2 = d6[..., :3].astype(np.float64), d6[..., 3:].astype(np.float64)
    b1 = a1 / np.maximum(np.linalg.norm(a1, axis=-1, keepdims=True), 1e-12)
    b2 = a2 - (b1 * a2).sum(-1, keepdims=True) * b1
    b2 = b2 / np.maximum(np.linalg.norm(b2, axis=-1, keepdims=True), 1e-12)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=-2)


def mat_to_quat(m):
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    q_abs = np.sqrt(np.maximum(0.0, np.stack([
        1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)))
    by = np.stack([
        np.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
        np.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], -1),
        np.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], -1),
        np.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], -1),
    ], -2)
    cand = by / (2.0 * np.maximum(q_abs[..., None], 0.1))
    best = q_abs.argmax(-1)
    return np.take_along_axis(cand, best[..., None, None], -2)[..., 0, :]


def quat_to_aa(q):
    n = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(n, q[..., :1])
    small = np.abs(angle) < 1e-6
    s = np.where(small, 0.5 - angle * angle / 48.0, np.sin(angle / 2.0) / np.where(small, 1.0, angle))
    return q[..., 1:] / s


def aa_to_mat(aa):
    aa = aa.astype(np.float64)
    angle = np.linalg.norm(aa, axis=-1, keepdims=True)
    small = np.abs(angle) < 1e-6
    s = np.where(small, 0.5 - angle * angle / 48.0, np.sin(angle / 2.0) / np.where(small, 1.0, angle))
    q = np.concatenate([np.cos(angle / 2.0), aa * s], -1).astype(np.float32).astype(np.float64)
    r, i, j, k = (q[..., c] for c in range(4))
    two_s = 2.0 / (q * q).sum(-1)
    o = np.stack([
        1 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r),
        two_s * (i * j + k * r), 1 - two_s * (i * i + k * k), two_s * (j * k - i * r),
        two_s * (i * k - j * r), two_s * (j * k + i * r), 1 - two_s * (i * i + j * j)], -1)
    return o.reshape(aa.shape[:-1] + (3, 3))


def mat_to_aa(m):
    return quat_to_aa(mat_to_quat(m)).astype(np.float32)


def mat_to_6d(m):
    return m[..., :2, :].reshape(m.shape[:-2] + (6,)).astype(np.float32)


def ax_from_6v(d6):
    return mat_to_aa(rot6d_to_mat(d6))


def ax_to_6v(aa):
    return mat_to_6d(aa_to_mat(aa).astype(np.float32))


class Normalizer:
    """preprocess.py:113-207: in-place float32 ops with the scaler's tensors."""

    def __init__(self, m):
        self.scale = np.array(m["scale"], np.float64)
        self.offset = np.array(m["offset"], np.float64)

    def normalize(self, x):
        y = (x.astype(np.float64) * self.scale).astype(np.float32)
        y = (y.astype(np.float64) + self.offset).astype(np.float32)
        return np.clip(y, -1, 1)

    def unnormalize(self, x):
        y = np.clip(x, -1, 1)
        y = (y.astype(np.float64) - self.offset).astype(np.float32)
        return (y.astype(np.float64) / self.scale).astype(np.float32)


def reortho(raw):
    """ax_to_6v(ax_from_6v(.)) of every joint: diffusion.py:1040-1090."""
    out = raw.copy()
    q = raw[..., 7:].reshape(raw.shape[:-1] + (22, 6))
    out[..., 7:] = ax_to_6v(ax_from_6v(q)).reshape(raw.shape[:-1] + (132,))
    return out


def swap_left_right(d6_rows):
    """infer_lodge.py:31-64 on (n, 132) 6D rows -> (n, 22, 3) axis-angle."""
    right = [2, 5, 8, 11, 14, 17, 19, 21]
    left = [1, 4, 7, 10, 13, 16, 18, 20]
    pose = ax_from_6v(d6_rows.reshape(-1, 22, 6))
    tmp = pose[:, right].copy()
    pose[:, right] = pose[:, left]
    pose[:, left] = tmp
    pose[:, :, 1:3] *= -1
    return pose


def mirror(mid):
    feet = np.concatenate([mid[:, 1:2], mid[:, 0:1], mid[:, 3:4], mid[:, 2:3]], -1)
    root = mid[:, 4:7].copy()
    root[:, 0] *= -1
    pose = ax_to_6v(swap_left_right(mid[:, 7:])).reshape(-1, 132)
    return np.concatenate([feet, root, pose], -1)


def constraint(orikey, norm, official):
    """Local_Module.py:170-224 for one 256-frame window."""
    ok = norm.normalize(orikey)
    m1 = ok[:4].copy()
    m1[:, 4] -= m1[0, 4]
    m1[:, 6] -= m1[0, 6]
    m2 = ok[-4:].copy()
    m2[:, 4] -= m2[0, 4]
    m2[:, 6] -= m2[0, 6]
    mid = ok[4:-4]
    mm = mirror(mid) if official else norm.normalize(mirror(orikey[4:-4]))
    value = np.zeros((256, F), np.float32)
    mask = np.zeros((256, F), np.float32)
    value[:4], value[-4:] = m1, m2
    value[28:36], value[60:68] = mid[:8], mm[:8]
    value[156:164], value[188:196] = mid[-8:], mm[-8:]
    for r in [slice(0, 4), slice(28, 36), slice(60, 68), slice(156, 164), slice(188, 196), slice(252, 256)]:
        mask[r, :4] = 1
        mask[r, 7:] = 1
    return value, mask


def alphas_cumprod(n=1000, s=0.008):
    """utils.py:78-86 (float64 betas), diffusion.py:82-86: float32 alphas, torch.cumprod (on the
    CPU it accumulates float32 in double and rounds each product)."""
    t = np.arange(n + 1, dtype=np.float64) / n + s
    a = np.cos(t / (1 + s) * np.pi / 2) ** 2
    a = a / a[0]
    betas = np.clip(1 - a[1:] / a[:-1], 0, 0.999).astype(np.float32)
    return np.cumprod((np.float32(1.0) - betas).astype(np.float64)).astype(np.float32)


class Stage:
    def __init__(self, music_file, denoiser_file):
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        self.music = ort.InferenceSession(str(PKG / music_file), opts)
        self.den = ort.InferenceSession(str(PKG / denoiser_file), opts)

    def sample(self, music, x, times, weights, ac, genre=None, style=None, cons=None):
        n = len(x)
        tok, hid = self.music.run(None, {
            "music": np.concatenate([music, music]),
            "keep": np.array([0.0] * n + [1.0] * n, np.float32)})
        for i, (t, nxt) in enumerate(zip(times[:-1], times[1:])):
            feed = {"x_t": np.concatenate([x, x]), "t": np.full(2 * n, t, np.int64),
                    "cond_tokens": tok, "cond_hidden": hid}
            if genre is not None:
                feed["genre"] = np.full(2 * n, genre, np.int64)
                feed["style_noise"] = np.concatenate([style[i, 0], style[i, 1]])
            out = self.den.run(None, feed)[0]
            unc, cond = out[:n], out[n:]
            model = unc + (cond - unc) * np.float32(weights[i])
            x0 = np.clip(model, -1, 1)
            a = ac[t]
            eps = (np.sqrt(np.float32(1) / a) * x - x0) / np.sqrt(np.float32(1) / a - np.float32(1))
            if nxt < 0:
                x = x0
                continue
            an = ac[nxt]
            sigma = np.float32(0)  # eta 0
            c = np.sqrt(np.float32(1) - an - sigma * sigma)
            x = (x0 * np.sqrt(an) + c * eps).astype(np.float32)
            if cons is not None:
                value, mask = cons
                x = np.where(mask > 0.5, value, x)
        return x


def run(manifest, frames, official, seed):
    lodge = manifest["lodge"]
    norm = Normalizer(manifest["motion"]["normalizer"])
    music = features(seed, frames)
    if official:
        locals_ = frames // 256
        padded = music[:locals_ * 256]
    else:
        locals_ = -(-frames // 256)
        total = max(locals_ * 256, 1024)
        padded = music[np.minimum(np.arange(total), frames - 1)]
    globals_ = -(-locals_ // 4)
    flag = locals_ % 4
    covered = locals_ * 256
    gstarts = [(max(covered, 1024) - 1024) if (g + 1) * 1024 > covered else g * 1024 for g in range(globals_)]
    if official:
        lstarts = [gstarts[k // 4] + (k % 4) * 256 for k in range(locals_)]
    else:
        lstarts = [k * 256 for k in range(locals_)]
    times = list(manifest["sampler"]["timesteps"]) + [-1]
    steps = len(times) - 1
    ac = alphas_cumprod()
    gx = normals(seed + 1, (globals_, 104, F))
    lx = normals(seed + 2, (locals_, 256, F))
    style = normals(seed + 3, (steps, 2, locals_, lodge["local"]["style_noise"]))

    gm = np.stack([padded[s:s + 1024] for s in gstarts])
    glob = Stage("global_music.onnx", "global_denoiser.onnx").sample(
        gm, gx, times, [lodge["global"]["guidance"]] * steps, ac)
    keys = reortho(norm.unnormalize(glob))
    rows = []
    for g in range(globals_):
        temp = keys[g].copy()
        if g > 0 and g == globals_ - 1 and flag != 0:
            temp = keys[g][104 - 8 - 24 * flag:].copy()
        if g > 0:
            temp[:8] = keys[g - 1][-8:]
        inner = temp[4:-4]
        rows += [inner[i * 24:(i + 1) * 24] for i in range(len(inner) // 24)]
    rows = rows[:locals_]
    cons = [constraint(r, norm, official) for r in rows]
    value = np.stack([c[0] for c in cons])
    mask = np.stack([c[1] for c in cons])
    ramp = lodge["local"]["guidance_ramp"]
    weights = np.clip(np.linspace(ramp[0], ramp[1], steps), None, lodge["local"]["guidance"])
    lm = np.stack([padded[s:s + 256] for s in lstarts])
    loc = Stage("local_music.onnx", "local_denoiser.onnx").sample(
        lm, lx, times, weights, ac, genre=3, style=style, cons=(value, mask))
    raw = reortho(norm.unnormalize(loc))
    if not official:
        for w in range(1, locals_):
            for c in (4, 6):
                shift = raw[w - 1, -1, c] + (raw[w - 1, -1, c] - raw[w - 1, -2, c]) - raw[w, 0, c]
                raw[w, :, c] += shift
    out = raw.reshape(-1, F)[: (locals_ * 256 if official else frames)]
    return glob, loc, value, mask, out, np.stack([rows[0], rows[-1]])


def main():
    manifest = tomllib.loads((PKG / "choreod-model.toml").read_text())
    arrays = {}
    for name, frames, official, seed in [("official", 1300, True, 100), ("fixed", 600, False, 200)]:
        glob, loc, value, mask, out, key_rows = run(manifest, frames, official, seed)
        # The raw keyframe rows of the first and the last Local window (the constraints' input).
        arrays[f"{name}_key_rows"] = key_rows
        # Every 4th keyframe of every Global window.
        arrays[f"{name}_global_rows"] = glob[:, ::4]
        # Rows of every Local window: the constrained ones and free ones between them.
        arrays[f"{name}_local_rows"] = loc[:, ROWS]
        # The constrained rows of the first and the last Local window, and the whole mask.
        arrays[f"{name}_constraint_rows"] = value[[0, -1]][:, CONSTRAINED]
        arrays[f"{name}_constraint_mask"] = mask
        arrays[f"{name}_features_rows"] = out[::13]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(OUT, **arrays)
    for k, v in arrays.items():
        print(k, v.shape)


CONSTRAINED = [*range(0, 4), *range(28, 36), *range(60, 68), *range(156, 164), *range(188, 196),
               *range(252, 256)]
ROWS = [0, 3, 4, 27, 28, 35, 36, 60, 67, 100, 156, 163, 188, 195, 196, 220, 251, 252, 255]

if __name__ == "__main__":
    main()
