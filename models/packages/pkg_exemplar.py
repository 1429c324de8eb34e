"""The `exemplar` package: the closed-form optimal denoiser of K real dance windows.

For the empirical distribution p(x0) = 1/K sum_i delta(x0 - e_i) and the forward process
x_t = sqrt(ab_t) x0 + sqrt(1 - ab_t) eps, the minimum-mean-square x0 estimate is

    x0_hat = sum_i w_i e_i,   w = softmax_i( -||x_t - sqrt(ab_t) e_i||^2 / (2 (1 - ab_t)) + m_i )

(m_i = 0 is the exact posterior; m_i is the music term below), and the epsilon the contract
asks for follows as eps = (x_t - sqrt(ab_t) x0_hat) / sqrt(1 - ab_t). All in normalised space.
The squared distance weights the window's second half by SECOND_HALF_WEIGHT (default 0: the
posterior given the first half, which identifies the exemplar; see the constant for why).

Music term (documented in the manifest description and exemplar/README.md):
    m_i = LAMBDA * cond * cos(music energy envelope of the window, joint-speed envelope of e_i)
The energy envelope is the per-frame mean over the 80 mel bands of the dB values, linearly
resampled from the 157 mel frames to the 150 motion frames; both envelopes are centred
(cosine of centred vectors = Pearson correlation), so loud-where-it-moves-fast exemplars win.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
from onnxscript import FLOAT, INT64, script
from onnxscript import opset18 as op

import pkg_common as C

SOURCE_NPY = "aistpp_fixture_joints30.npy"
# Exemplar windows are cut from the source played as a LOOP (see derive_source) at a stride that
# divides the 75-frame window stride of long songs: then the second half of every exemplar is
# the first half of another one (e_j[75:] = e_{j+5}[:75]), so EDGE's overlap consistency
# (window i+1's first half := window i's second half) always has a seamless continuation, for
# songs of any length. 15 frames = 0.5 s; with the 270-frame loop this gives K = 18.
EXEMPLAR_STRIDE = 15
# Loop search range (frames at 30 fps): long enough for a window and a half, a multiple of the
# exemplar stride so the cyclic windows tile the loop exactly.
LOOP_MIN, LOOP_MAX = 225, 345
# Normalisation floor (metres): a coordinate that barely moves across the exemplars (e.g. a
# bone nearly aligned with an axis) would otherwise get a tiny std and turn millimetre jitter
# into unit-scale noise; 1 cm is far below any joint's real motion range in a dance.
STD_FLOOR = 0.01
# Music logit scale: cosine similarities lie in [-1, 1]; LAMBDA = 4 makes the best-matching
# exemplar up to e^8 more likely than the worst at high noise, where the data term is flat,
# and is negligible at low noise, where the data term dominates (it scales with 1/(1-ab)).
MUSIC_LAMBDA = 4.0
# Added to the squared norm of the centred music envelope (dB^2 summed over 150 frames):
# near-silent or constant music has no envelope, and its cosine must go to 0 (no preference)
# rather than amplify rounding noise into a strong vote.
ENVELOPE_EPS = 1.0
# Feet-on-floor grounding: the AIST++ world frame does not put the floor at y = 0 (the fixture's
# lowest ankle/toe sits ~0.88 m up with the EDGE rest offsets), so the source is shifted
# vertically so that the lowest foot joint of the clip is at y = 0.
FOOT_JOINTS = (7, 8, 10, 11)  # l/r ankle, l/r toes (Stanford-TML/EDGE:vis.py smpl_joints)
# Weight of the window's second half (frames 75..149) in the posterior's squared distance; the
# first half always has weight 1. 1.0 would be the textbook optimal denoiser of whole windows.
# 0.0 makes the posterior E[x0 | first half of x_t]: in this data the first half identifies the
# exemplar, and the first half is exactly what EDGE's long-form sampler copies from the previous
# window (and what seed-frame in-painting fixes), so each window continues its predecessor
# instead of racing it. Measured on the 61 s fixture song (24 windows, DDIM 50, 3 seeds x
# guidance 1/2.5): windows that do not continue their predecessor 14-19 of 23 with 1.0,
# 10-12 with 0.3, 6-10 with 0.0 (models/packages/README.md, "exemplar and long songs").
SECOND_HALF_WEIGHT = 0.0
# Sampler default written into the manifest: with set_alpha_to_one = true the last DDIM step
# returns x0_hat itself (alpha_prev = 1), i.e. exactly a real exemplar, instead of stopping at
# the noise level of alphas_cumprod[0] (sqrt(1 - ab_0) = 1 %, which also keeps ~1 % of any
# disagreement the overlap copy left behind).
SET_ALPHA_TO_ONE = True
# Sampler default eta = 1 as EDGE samples (Stanford-TML/EDGE:model/diffusion.py ddim_sample).
# Fresh noise at every step washes out the "late decision" offsets the overlap copy hands from
# window to window: windows not continuing their predecessor on the 61 s fixture song drop
# from 6-10 of 23 (eta 0) to 2-5 (eta 1), measured as in models/packages/README.md.
SAMPLER_ETA = 1.0


def find_loop(joints: np.ndarray) -> tuple[int, int]:
    """(a, b): frames whose pose and velocity match best, b - a a multiple of EXEMPLAR_STRIDE.

    Score = rms root-relative joint difference + 5 x rms velocity difference (metres; velocity
    weighted up because a velocity jump is what a viewer sees at a loop point).
    """
    f = C.joints_to_features(joints)
    rel, vel = f[:, 3:], np.diff(f, axis=0)
    best = None
    for length in range(LOOP_MIN, LOOP_MAX + 1, EXEMPLAR_STRIDE):
        for a in range(1, vel.shape[0] - length):
            b = a + length
            score = (np.sqrt(((rel[b] - rel[a]) ** 2).mean()) + 5.0 * np.sqrt(((vel[b] - vel[a]) ** 2).mean()))
            if best is None or score < best[0]:
                best = (score, a, b)
    return best[1], best[2]


def derive_source(pkl_path: Path, out_npy: Path) -> tuple[np.ndarray, dict]:
    """AIST++ motion .pkl (60 fps) -> a seamless loop of joints (L, 24, 3) float32 at 30 fps.

    1. SMPL FK of the fixture (EDGE vis.py offsets), every other frame (60 -> 30 fps).
    2. The dance repeats: find frames a < b with matching pose (find_loop) and keep [a, b).
    3. Close the loop exactly: spread the residual between frame b and frame a linearly over
       the loop, in rotation space per joint (R'_f = exp(s log(R_a R_b^T)) R_f, s = (f-a)/L) and
       on the root translation, then redo FK, so bone lengths stay exact and frame L-1 flows
       into frame 0 the way frame b-1 flowed into frame b.
    4. Shift vertically so the lowest ankle/toe of the loop is at y = 0.
    """
    from scipy.spatial.transform import Rotation

    with open(pkl_path, "rb") as f:
        d = pickle.load(f)  # trusted fixture (build script only)
    poses = np.asarray(d["smpl_poses"], dtype=np.float64)
    # Some readers say (N, 24, 3), others (N, 72): reshape defensively (reference-facts.md §4).
    poses = poses.reshape(poses.shape[0], C.N_JOINTS, 3)[::2]  # 60 -> 30 fps (EDGE data/slice.py)
    scaling = float(np.asarray(d["smpl_scaling"], dtype=np.float64).ravel()[0])
    # root = trans / scaling, metres, y-up (google/aistplusplus_api demos/extract_motion_feats.py)
    root = (np.asarray(d["smpl_trans"], dtype=np.float64).reshape(-1, 3) / scaling)[::2]
    a, b = find_loop(C.smpl_forward_kinematics(poses, root))
    length = b - a
    s = (np.arange(length) / length)[:, None]
    rot = Rotation.from_rotvec(poses[a:b + 1].reshape(-1, 3)).as_matrix().reshape(length + 1, C.N_JOINTS, 3, 3)
    resid = Rotation.from_matrix(rot[0] @ np.swapaxes(rot[-1], -1, -2)).as_rotvec()      # (24, 3)
    fix = Rotation.from_rotvec((s[:, :, None] * resid[None]).reshape(-1, 3)).as_matrix()
    new_rot = fix.reshape(length, C.N_JOINTS, 3, 3) @ rot[:-1]
    new_poses = Rotation.from_matrix(new_rot.reshape(-1, 3, 3)).as_rotvec().reshape(length, C.N_JOINTS, 3)
    new_root = root[a:b] - s * (root[b] - root[a])
    joints = C.smpl_forward_kinematics(new_poses, new_root)
    floor = joints[:, FOOT_JOINTS, 1].min()
    joints[..., 1] -= floor
    out = joints.astype(np.float32)
    np.save(out_npy, out, allow_pickle=False)
    info = {"loop_start_30fps": a, "loop_end_30fps": b, "frames": length, "floor_shift_m": float(floor),
            "max_joint_rotation_fix_deg": float(np.degrees(np.linalg.norm(resid, axis=1).max())),
            "root_fix_m": float(np.linalg.norm(root[b] - root[a]))}
    return out, info


def n_exemplars(joints: np.ndarray) -> int:
    return joints.shape[0] // EXEMPLAR_STRIDE


def exemplar_windows(joints: np.ndarray, k: int) -> np.ndarray:
    """The first k cyclic windows of 150 frames at stride EXEMPLAR_STRIDE, (k, 150, 72) float64."""
    feats = C.joints_to_features(joints.astype(np.float64))
    n_max = n_exemplars(joints)
    if feats.shape[0] < C.WINDOW_FRAMES or feats.shape[0] % EXEMPLAR_STRIDE:
        raise SystemExit(f"source loop of {feats.shape[0]} frames: need >= {C.WINDOW_FRAMES}, "
                         f"a multiple of {EXEMPLAR_STRIDE}")
    if not 1 <= k <= n_max:
        raise SystemExit(f"--exemplars must be in 1..{n_max} for a {feats.shape[0]}-frame loop, got {k}")
    idx = (np.arange(k)[:, None] * EXEMPLAR_STRIDE + np.arange(C.WINDOW_FRAMES)[None]) % feats.shape[0]
    return feats[idx]


def speed_envelope(joints: np.ndarray, k: int) -> np.ndarray:
    """(k, T) summed joint speed per frame (m/frame) of each cyclic window, world joints.

    Computed on the loop (frame 0 follows frame L-1), then cut like the windows.
    """
    j = joints.astype(np.float64)
    sp = np.linalg.norm(j - np.roll(j, 1, axis=0), axis=-1).sum(axis=-1)
    idx = (np.arange(k)[:, None] * EXEMPLAR_STRIDE + np.arange(C.WINDOW_FRAMES)[None]) % j.shape[0]
    return sp[idx]


def mel_to_motion_matrix() -> np.ndarray:
    """(157, 150) linear-interpolation matrix: mel frame i at i*hop/sr s -> motion frame j at j/fps s."""
    w = np.zeros((C.MUSIC_FRAMES, C.WINDOW_FRAMES), dtype=np.float64)
    for j in range(C.WINDOW_FRAMES):
        pos = j / C.FPS * C.SAMPLE_RATE / C.HOP  # in mel frames; max 155.2 < 156, always inside
        i0 = int(np.floor(pos))
        frac = pos - i0
        w[i0, j] += 1.0 - frac
        w[min(i0 + 1, C.MUSIC_FRAMES - 1), j] += frac
    return w


def build_graph(ex_norm: np.ndarray, speed: np.ndarray, lam: float, gamma: float):
    """The denoiser as an onnxscript function over constants captured from this scope."""
    k = ex_norm.shape[0]
    ab = C.alphas_cumprod()
    # Tables computed in float64 and stored as float32 (brief: "compute in float64, store float32").
    sqrt_ab_tab = np.sqrt(ab).astype(np.float32)
    sqrt_1mab_tab = np.sqrt(1.0 - ab).astype(np.float32)
    inv_2var_tab = (1.0 / (2.0 * (1.0 - ab))).astype(np.float32)
    ex_flat = ex_norm.reshape(k, -1).astype(np.float32)           # (K, T*D)
    sp_c = speed - speed.mean(axis=1, keepdims=True)
    sp_hat = (sp_c / np.linalg.norm(sp_c, axis=1, keepdims=True)).T.astype(np.float32)  # (T, K)
    mel2mot = mel_to_motion_matrix().astype(np.float32)            # (F, T)
    lam32 = np.array([lam], dtype=np.float32)
    frame_w = np.repeat(np.where(np.arange(C.WINDOW_FRAMES) < C.STRIDE_FRAMES, 1.0, gamma), C.DIM).astype(np.float32)
    env_eps = np.array([ENVELOPE_EPS], dtype=np.float32)

    @script()
    def denoiser(x_t: FLOAT["N", 150, 72], t: INT64["N"], music: FLOAT["N", 157, 80],
                 cond: FLOAT["N"]) -> FLOAT["N", 150, 72]:
        axis1 = op.Constant(value_ints=[1])
        sab = op.Gather(op.Constant(value=sqrt_ab_tab), t)         # (N,), t out of 0..999 -> ORT error
        s1mab = op.Gather(op.Constant(value=sqrt_1mab_tab), t)
        inv2v = op.Gather(op.Constant(value=inv_2var_tab), t)

        # Data term: x_t-space squared distance to each scaled exemplar, computed as a difference
        # (not expanded into |x|^2 - 2x.e + |e|^2, which cancels catastrophically in float32 when
        # 1 - ab is ~1e-4 and the logits are ~1e7).
        xf = op.Reshape(x_t, op.Constant(value_ints=[0, 1, -1]))   # (N, 1, T*D)
        sab3 = op.Unsqueeze(sab, op.Constant(value_ints=[1, 2]))   # (N, 1, 1)
        ex = op.Constant(value=ex_flat)                            # (K, T*D), stored once
        diff = op.Sub(xf, op.Mul(sab3, op.Unsqueeze(ex, op.Constant(value_ints=[0]))))  # (N, K, T*D)
        d2 = op.ReduceSum(op.Mul(op.Mul(diff, diff), op.Constant(value=frame_w)), op.Constant(value_ints=[2]),
                          keepdims=0)                                       # (N, K)
        data_logit = op.Neg(op.Mul(d2, op.Unsqueeze(inv2v, axis1)))

        # Music term: cosine between the centred energy envelope and each centred speed envelope.
        energy = op.ReduceMean(music, op.Constant(value_ints=[2]), keepdims=0)  # (N, F) mean dB
        env = op.MatMul(energy, op.Constant(value=mel2mot))                      # (N, T)
        env_c = op.Sub(env, op.ReduceMean(env, axis1, keepdims=1))
        norm = op.Sqrt(op.Add(op.ReduceSumSquare(env_c, axis1, keepdims=1), op.Constant(value=env_eps)))
        sim = op.Div(op.MatMul(env_c, op.Constant(value=sp_hat)), norm)          # (N, K)
        music_logit = op.Mul(op.Mul(sim, op.Constant(value=lam32)), op.Unsqueeze(cond, axis1))

        logits = op.Add(data_logit, music_logit)
        # Subtract the row max explicitly so exp never overflows whatever ORT's Softmax does.
        logits = op.Sub(logits, op.ReduceMax(logits, axis1, keepdims=1))
        w = op.Softmax(logits, axis=1)                                            # (N, K)
        x0_flat = op.MatMul(w, ex)                                                # (N, T*D)
        x0 = op.Reshape(x0_flat, op.Shape(x_t))
        pred = op.Div(op.Sub(x_t, op.Mul(sab3, x0)), op.Unsqueeze(s1mab, op.Constant(value_ints=[1, 2])))
        return pred

    return denoiser.to_model_proto()


def description(k: int, lam: float, gamma: float) -> str:
    half = ("from the window's first half (frames 0-74), " if gamma == 0.0 else
            f"with the second half weighted {gamma:g}, ")
    return (
        f"Closed-form denoiser over K={k} real dance windows (5 s, 30 fps) cut from a loop of the AIST++ "
        "motion gBR_sBM_cAll_d04_mBR0_ch01 (CC BY 4.0, AIST++ / AIST Dance DB): x0_hat = softmax-weighted "
        f"mean of the exemplars, weights = Gaussian posterior given x_t and t computed {half}epsilon follows. "
        f"Music conditioning: logit_i += {lam:g} * cond * cosine(window's per-frame mel energy envelope (mean "
        "dB over the 80 bands, resampled to the motion frames, centred), exemplar i's joint-speed envelope "
        "(centred)); cond = 0 removes it. With K=1 every correct sampler returns that exemplar."
    )


def readme_text(k: int, lam: float, loop_frames: int, gamma: float) -> str:
    return f"""# `exemplar` — the closed-form denoiser over real AIST++ dance windows

Built by `models/packages/build.py exemplar --exemplars {k}` from
`models/packages/exemplar-source/{SOURCE_NPY}` (see the README there for provenance and licence:
AIST++ annotations, CC BY 4.0 — credit AIST++ (Li et al., ICCV 2021) and the AIST Dance Video DB).

## What the network computes

Exemplars e_1..e_K: windows of 150 frames (5 s at 30 fps) cut from the {loop_frames}-frame dance
loop (the fixture's routine repeats; see exemplar-source/README.md) at a stride of
{EXEMPLAR_STRIDE} frames, wrapping around the loop ({loop_frames // EXEMPLAR_STRIDE} windows cover it; `--exemplars K`
keeps the first K), in the contract representation (root xyz, then joints 1..23 minus the root; metres, y-up,
floor at y = 0) and normalised with the package's mean/std (computed over all K x 150 frames;
std floored at {STD_FLOOR} m).

Given normalised x_t and the training step t (alphas_cumprod ab_t of the linear schedule
1e-4 -> 0.02 over 1000 steps, computed in float64, stored as float32 tables gathered by t):

    d2_i    = sum_f c_f ||x_t[f] - sqrt(ab_t) e_i[f]||^2,  c_f = 1 for f < 75, {gamma:g} for f >= 75
    logit_i = -d2_i / (2 (1 - ab_t)) + {lam:g} * cond * sim_i
    w = softmax(logit - max(logit)),   x0_hat = sum_i w_i e_i
    pred = eps = (x_t - sqrt(ab_t) x0_hat) / sqrt(1 - ab_t)

With c_f = 1 everywhere and no music term this is the exact posterior mean of the empirical
distribution (the optimal denoiser). This build uses c_f = {gamma:g} on the second half: the
posterior is then E[x0 | first half of x_t], still exact for that observation because the
first 75 frames identify the exemplar, and it makes windows continue the one before them far
more often under EDGE's long-form sampler, which copies window i's second half into window
i+1's first half at every step (with whole-window weights the two halves of a window race and
the window often settles on a different exemplar than its copied half; see ../README.md). Either way a
correct sampler produces real dance motion, and with K = 1 it returns the single exemplar
exactly for any noise and any music (oracle for sampler tests).

The manifest sets `set_alpha_to_one = true`: DDIM's last step then returns x0_hat, a real
exemplar, instead of stopping at the noise level of alphas_cumprod[0]; and `eta = 1` (as EDGE
samples), whose fresh noise per step makes long songs chain their windows more reliably.

Long songs: the stride {EXEMPLAR_STRIDE} divides the 75-frame window stride, so the second half of
exemplar j is the first half of exemplar j + {75 // EXEMPLAR_STRIDE} (mod K = {loop_frames // EXEMPLAR_STRIDE}). EDGE's overlap
consistency (window i+1's first half := window i's second half at every step) therefore always
has an exact continuation, for songs of any length (with the full set; a `--exemplars K` subset
breaks the cycle). Most windows take it: on the 61 s fixture song 18-21 of 23 continue their
predecessor exactly with these defaults; the others are cross-faded by the stitcher (see
../README.md for what that does to bone lengths).

## Music conditioning (real, small, documented)

sim_i = cos(a - mean(a), s_i - mean(s_i)), i.e. the Pearson correlation over the 150 frames
between
- a: the music window's energy envelope = mean over the 80 mel bands of the log-mel dB values
  per mel frame, linearly interpolated from the 157 mel frames (i * 512 / 16000 s) to the 150
  motion frames (j / 30 s), and
- s_i: exemplar i's joint-speed envelope = sum over the 24 joints of |p_j(f) - p_j(f-1)| (m/frame).

The norm of the centred music envelope gets +{ENVELOPE_EPS:g} dB^2 so silence or a constant
level gives sim = 0 (no preference). cond = 0 (the unconditional row of classifier-free guidance)
drops the term. Effect: at high noise, where the data term is flat, exemplars whose movement
swells where the music gets louder are preferred (at most e^{2 * lam:g} between the best and the
worst match); at low noise the data term dominates and the sample settles on real motion.
On the fixture songs (vibe_ace, hungarian_dance) the similarities span about -0.4..0.44 and the
best exemplar of a window gets about twice the uniform share at high noise: a real but gentle
push, which mostly chooses the phase of the loop a song starts on.

## Files

- `denoiser.onnx` — opset 18, inputs x_t [N,150,72] f32, t [N] i64, music [N,157,80] f32,
  cond [N] f32; output pred [N,150,72] f32 (epsilon).
- `choreod-model.toml` — manifest (mean/std, schedule, sampler defaults, sha256 of the ONNX file).

Checked by `build.py check models/packages/exemplar` (onnxruntime, N = 1 and 4).
"""


def build(out_dir: Path, source_npy: Path, k: int | None, lam: float = MUSIC_LAMBDA,
          gamma: float = SECOND_HALF_WEIGHT) -> int:
    joints = np.load(source_npy, allow_pickle=False)
    if joints.ndim != 3 or joints.shape[1:] != (C.N_JOINTS, 3):
        raise SystemExit(f"{source_npy}: expected joints (T, 24, 3), got {joints.shape}")
    k = n_exemplars(joints) if k is None else k
    windows = exemplar_windows(joints, k)
    frames = windows.reshape(-1, C.DIM)
    # float64 accumulation over K*150 frames, stored float32
    mean = frames.mean(axis=0).astype(np.float32)
    std = np.maximum(frames.std(axis=0), STD_FLOOR).astype(np.float32)
    ex_norm = (windows - mean.astype(np.float64)) / std.astype(np.float64)
    speed = speed_envelope(joints, k)
    model = build_graph(ex_norm, speed, lam, gamma)
    model.doc_string = description(k, lam, gamma)
    out_dir.mkdir(parents=True, exist_ok=True)
    sha = C.save_model(model, out_dir / "denoiser.onnx")
    C.write_manifest(out_dir, name="exemplar", description=description(k, lam, gamma), mean=mean, std=std,
                     onnx_file="denoiser.onnx", onnx_sha256=sha, eta=SAMPLER_ETA,
                     set_alpha_to_one=SET_ALPHA_TO_ONE)
    (out_dir / "README.md").write_text(readme_text(k, lam, joints.shape[0], gamma), encoding="utf-8")
    return k
