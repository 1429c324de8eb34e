"""The `exemplar` package: a closed-form denoiser over a real dance loop, retimed onto the beat.

The data: a seamless 9 s loop of real AIST++ dance (exemplar-source/). Its kinematic beats
(Bailando's: local minima of the smoothed mean joint speed) fall one per beat of the 80 BPM
music it was danced to (12 in the 270-frame loop); the build retimes the loop slightly so they
sit exactly on that grid.

Per window, from the music alone (so choreod computes it once per batch, not per step):
1. onset strength of the 157 log-mel frames: mean over the 80 bands of the half-wave-rectified
   first difference (librosa's onset_strength on a dB mel spectrogram), credited to the frame
   librosa credits it to, divided by its window mean;
2. a comb search over music beat periods Q (60-180 BPM, 1 % steps) and phases (every motion
   frame): log of the mean onset at the comb's teeth plus librosa's tempo prior; per tempo its
   best phase; the TEMPO_GROUPS best local maxima over tempo, those within TEMPO_AGREEMENT of
   the best kept (the others replaced by the best);
3. per tempo group, the loop played at the speed that puts one dance beat on every music beat
   (every second one below HALF_TIME_BELOW_S), starting on each dance beat (or half beat at half
   time) at the comb's first tooth: 24 candidate windows per group, read by linear
   interpolation between the loop's frames. Every candidate's kinematic beats fall on the teeth.

Then the closed-form posterior over the candidates, in normalised space:

    x0_hat = sum_i w_i e_i,   w = softmax_i( -sum_f c_f ||x_t[f] - sqrt(ab_t) e_i[f]||^2 / (2 (1 - ab_t))
                                             + MUSIC_WEIGHT * (score of i's tempo - best score) )

(c_f = 1 on the window's first half, SECOND_HALF_WEIGHT on the second), and the epsilon the
contract asks for is eps = (x_t - sqrt(ab_t) x0_hat) / sqrt(1 - ab_t). cond = 0 (the
unconditional row) plays the loop at its own tempo from its first beat: no music at all.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
from onnxscript import FLOAT, INT64, script
from onnxscript import opset18 as op

import pkg_common as C

SOURCE_NPY = "aistpp_fixture_joints30.npy"
# Loop lengths searched in steps of 15 frames (0.5 s) in LOOP_MIN..LOOP_MAX frames at 30 fps: a
# window and a half at least. The committed source (exemplar-source/) was derived with these.
LOOP_STEP = 15
LOOP_MIN, LOOP_MAX = 225, 345
# Frames before the loop point over which the closing rotation residual is eased in. Spreading
# it over the whole loop (as before) tilts the body by up to 11 degrees mid-loop, enough to move
# the toes across the 5 cm contact height of the skating metric: `choreod eval` of the loop gave
# skate_ratio 0.028 spread over 270 frames, 0.011 (the untouched fixture's 0.011) over 60. The
# root's 0.22 m drift stays spread over the whole loop (2.4 cm/s): eased in over 60 frames it
# moved planted feet by 11 cm/s (skate_ratio of the loop played 1.2x fast: 0.020 vs 0.013).
CLOSE_BLEND_FRAMES = 60
# Normalisation floor (metres): a coordinate that barely moves across the exemplars (e.g. a
# bone nearly aligned with an axis) would otherwise get a tiny std and turn millimetre jitter
# into unit-scale noise; 1 cm is far below any joint's real motion range in a dance.
STD_FLOOR = 0.01
# Feet-on-floor grounding: the AIST++ world frame does not put the floor at y = 0 (the fixture's
# lowest ankle/toe sits ~0.88 m up with the EDGE rest offsets), so the source is shifted
# vertically so that the lowest foot joint of the clip is at y = 0.
FOOT_JOINTS = (7, 8, 10, 11)  # l/r ankle, l/r toes (Stanford-TML/EDGE:vis.py smpl_joints)
# Weight of the window's second half (frames 75..149) in the posterior's squared distance; the
# first half always has weight 1. 1.0 would be the textbook optimal denoiser of whole windows.
# 0.0 makes the posterior E[x0 | first half of x_t]: the first half identifies the candidate,
# and the first half is exactly what EDGE's long-form sampler copies from the previous window
# (and what seed-frame in-painting fixes), so each window continues its predecessor instead of
# racing it (measured in models/packages/README.md, "exemplar and long songs").
SECOND_HALF_WEIGHT = 0.0
# Sampler default written into the manifest: with set_alpha_to_one = true the last DDIM step
# returns x0_hat itself (alpha_prev = 1), i.e. exactly one candidate, instead of stopping at
# the noise level of alphas_cumprod[0] (sqrt(1 - ab_0) = 1 %).
SET_ALPHA_TO_ONE = True
# Sampler default eta = 1 as EDGE samples (Stanford-TML/EDGE:model/diffusion.py ddim_sample):
# fresh noise at every step washes out the late decisions the overlap copy hands from window
# to window (models/packages/README.md, "exemplar and long songs").
SAMPLER_ETA = 1.0

# --- Beat warp ------------------------------------------------------------------------------
# Kinematic beats as Bailando's beat_align_score.py finds them (lisiyao21/Bailando cc90b98,
# utils/beat_align_score.py:43-48): local minima of the Gaussian-smoothed (sigma 5 frames at
# 60 fps) mean joint speed; the loop is resampled to 60 fps for it, as `choreod eval` scores.
KINEMATIC_SMOOTH_SIGMA_60 = 5.0
# Candidate music beat periods (seconds): 60..180 BPM, the range of choreod's beat tracker's
# prior mass (start 120 BPM, one octave either side).
MUSIC_PERIOD_MIN_S, MUSIC_PERIOD_MAX_S = 1.0 / 3.0, 1.0
# Period grid ratio: a 1 % tempo error drifts by 25 ms at the ends of a 5 s window aligned in
# its middle, half the 50 ms sigma of the BAS at 60 fps.
MUSIC_PERIOD_RATIO = 1.01
# Width of a comb tooth (seconds): the onset envelope is sampled every 32 ms (hop 512 at
# 16 kHz), so a tooth narrower than ~20 ms would fall between frames.
TOOTH_SIGMA_S = 0.02
# Added to the window's mean onset strength (dB per mel frame) before normalising by it: in
# silence or a constant tone every comb scores 0 and only the tempo prior speaks.
ONSET_EPS = 0.1
# Added to a comb's score (mean normalised onset at its teeth) before its logarithm.
SCORE_EPS = 0.01
# Tempo prior, as choreod's tracker and librosa weigh tempi (librosa 0.11 feature/rhythm.py
# `tempo`: start_bpm = 120, std_bpm = 1.0; dsp/src/beats.rs `estimate_tempo`): log score
# -0.5 (log2(bpm / 120) / 1)^2 added to the log comb score.
PRIOR_BPM, PRIOR_OCTAVES = 120.0, 1.0
# Tempi a window offers the posterior: the TEMPO_GROUPS best local maxima of the tempo score
# (a maximum over +-TEMPO_PEAK_HALF_WIDTH grid steps, i.e. +-5 %), each at its best phase; a
# group whose log score is more than TEMPO_AGREEMENT behind the best is replaced by the best.
# Why groups: at low noise the data term (which grows as 1 / (1 - ab)) makes a window continue
# its predecessor whenever that continuation is among its candidates, so offering the
# predecessor's tempo avoids cross-fading two tempi at the seam (which slides the feet). Why the
# agreement band: offered at any score, a continuation wins even where the music has moved on
# (windows then keep the first window's tempo). Measured on vibe_ace only, mean of seeds 0-3
# (bas_music_beats, skate_ratio): one group 0.318, 0.020; band 0.05: 0.308, 0.023; 0.1: 0.381,
# 0.016; 0.15: 0.336, 0.012; 0.3: 0.168, 0.015 (BENCHMARKS.md, "eval").
TEMPO_GROUPS = 3
TEMPO_AGREEMENT = 0.15
TEMPO_PEAK_HALF_WIDTH = 5
# The music logit of a group: MUSIC_WEIGHT x (its log score - the best's), so at high noise the
# best tempo leads. Barely matters inside the band (vibe_ace: 1 -> 0.335, 4 -> 0.336, 10 -> 0.333).
MUSIC_WEIGHT = 4.0
# Below this music beat period (seconds) the dance takes every second beat (the loop at
# 0.375 / Q x its speed) rather than every beat (0.75 / Q x): the loop played faster than
# 1.1x skates (`choreod eval` of the loop alone: skate_ratio 0.006 at 1.0x, 0.013 at 1.1x, 0.020
# at 1.2x, 0.038 at 1.3x), slower is fine (0.002 at 0.65x). 0.6 s (speeds up to 1.25x) was
# chosen on vibe_ace: 0.66 gave bas_music_beats 0.302, skate 0.008; 0.6 gave 0.336, 0.012.
HALF_TIME_BELOW_S = 0.6


def find_loop(joints: np.ndarray) -> tuple[int, int]:
    """(a, b): frames whose pose and velocity match best, b - a a multiple of LOOP_STEP.

    Score = rms root-relative joint difference + 5 x rms velocity difference (metres; velocity
    weighted up because a velocity jump is what a viewer sees at a loop point).
    """
    f = C.joints_to_features(joints)
    rel, vel = f[:, 3:], np.diff(f, axis=0)
    best = None
    for length in range(LOOP_MIN, LOOP_MAX + 1, LOOP_STEP):
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
    3. Close the loop exactly: ease in the rotation residual between frame b and frame a per
       joint over the last CLOSE_BLEND_FRAMES frames (R'_f = exp(s log(R_a R_b^T)) R_f, s a
       smoothstep), spread the root translation residual linearly over the whole loop, then
       redo FK, so bone lengths stay exact and frame L-1 flows into frame 0 the way frame b-1
       flowed into frame b.
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
    ramp = np.clip((np.arange(length) - (length - CLOSE_BLEND_FRAMES)) / CLOSE_BLEND_FRAMES, 0.0, 1.0)
    s = (ramp * ramp * (3.0 - 2.0 * ramp))[:, None]  # smoothstep: 0 until the blend, 1 at frame b
    s_root = (np.arange(length) / length)[:, None]   # the root drift: spread over the whole loop
    rot = Rotation.from_rotvec(poses[a:b + 1].reshape(-1, 3)).as_matrix().reshape(length + 1, C.N_JOINTS, 3, 3)
    resid = Rotation.from_matrix(rot[0] @ np.swapaxes(rot[-1], -1, -2)).as_rotvec()      # (24, 3)
    fix = Rotation.from_rotvec((s[:, :, None] * resid[None]).reshape(-1, 3)).as_matrix()
    new_rot = fix.reshape(length, C.N_JOINTS, 3, 3) @ rot[:-1]
    new_poses = Rotation.from_matrix(new_rot.reshape(-1, 3, 3)).as_rotvec().reshape(length, C.N_JOINTS, 3)
    new_root = root[a:b] - s_root * (root[b] - root[a])
    joints = C.smpl_forward_kinematics(new_poses, new_root)
    floor = joints[:, FOOT_JOINTS, 1].min()
    joints[..., 1] -= floor
    out = joints.astype(np.float32)
    np.save(out_npy, out, allow_pickle=False)
    info = {"loop_start_30fps": a, "loop_end_30fps": b, "frames": length, "floor_shift_m": float(floor),
            "max_joint_rotation_fix_deg": float(np.degrees(np.linalg.norm(resid, axis=1).max())),
            "root_fix_m": float(np.linalg.norm(root[b] - root[a]))}
    return out, info


def kinematic_beats_60(joints: np.ndarray) -> np.ndarray:
    """Bailando's kinematic beats of a 30 fps clip (T, 24, 3), in frames at 60 fps.

    Resampled to 60 fps by linear interpolation, as `choreod eval` scores; then local minima of
    the smoothed mean joint speed (beat k sits between 60 fps frames k and k + 1).
    """
    from scipy.ndimage import gaussian_filter1d

    j = joints.astype(np.float64)
    t60 = np.arange(2 * j.shape[0] - 1) / 2.0
    lo = np.floor(t60).astype(int)
    hi = np.minimum(lo + 1, j.shape[0] - 1)
    frac = (t60 - lo)[:, None, None]
    j60 = j[lo] * (1.0 - frac) + j[hi] * frac
    speed = np.linalg.norm(np.diff(j60, axis=0), axis=-1).mean(axis=-1)
    s = gaussian_filter1d(speed, KINEMATIC_SMOOTH_SIGMA_60)
    return np.flatnonzero((s[1:-1] < s[:-2]) & (s[1:-1] < s[2:])) + 1


def kinematic_beats(joints: np.ndarray) -> np.ndarray:
    """Kinematic beats of a 30 fps LOOP, in (fractional) 30 fps frames of the loop.

    The loop is tiled three times and the beats are read off the middle copy, so the smoothing
    sees real motion on both sides.
    """
    n = joints.shape[0]
    beats = kinematic_beats_60(np.concatenate([joints, joints, joints]))
    mid = beats[(beats >= 2 * n) & (beats < 4 * n)]
    return mid / 2.0 - n


def beat_grid(joints: np.ndarray) -> tuple[float, float]:
    """(period, offset) in loop frames: the regular grid the loop's kinematic beats sit on.

    period = loop length / number of beats; offset = circular mean of the beats modulo the
    period. Refuses a source whose beats are not regular (spread over a quarter period).
    """
    beats = kinematic_beats(joints)
    if beats.size < 2:
        raise SystemExit(f"the source loop has {beats.size} kinematic beats: need a rhythmic dance")
    period = joints.shape[0] / beats.size
    angle = 2.0 * np.pi * beats / period
    mean = np.angle(np.exp(1j * angle).mean())
    offset = float((mean / (2.0 * np.pi) * period) % period)
    spread = np.abs((beats - offset + period / 2.0) % period - period / 2.0).max()
    if spread > period / 4.0:
        raise SystemExit(f"the loop's kinematic beats are irregular (off the grid by {spread:.1f} frames)")
    return period, offset


def retime_to_grid(joints: np.ndarray, period: float, offset: float) -> np.ndarray:
    """The loop re-timed so that its kinematic beat k sits exactly at offset + k period.

    A piecewise-linear, cyclic, monotone time map through the knots (grid position of beat k ->
    measured beat k), read by linear interpolation between the loop's frames: each beat
    interval is stretched or squeezed by at most 1.25 of 22.5 frames on the fixture, and the
    interpolation moves bone lengths by at most 4 mm (the rigid fit after the denoiser
    restores them).
    """
    n = joints.shape[0]
    beats = kinematic_beats(joints)
    grid = offset + period * np.arange(beats.size)
    if beats.size != round(n / period) or np.any(np.diff(beats) <= 0):
        raise SystemExit("the loop's kinematic beats do not fit its beat grid")
    knots_grid = np.concatenate([grid - n, grid, grid + n])
    knots_loop = np.concatenate([beats - n, beats, beats + n])
    tau = np.interp(np.arange(n), knots_grid, knots_loop) % n
    lo = np.floor(tau).astype(int)
    frac = (tau - lo)[:, None, None]
    j = joints.astype(np.float64)
    return j[lo] * (1.0 - frac) + j[(lo + 1) % n] * frac


def tempo_grid(period_frames: float) -> dict[str, np.ndarray]:
    """Per candidate music beat period Q (n_tempi of them, 1 % apart): what the dance does with it.

    `period_s` Q, `log_prior` of its tempo, `beats_per_dance_beat` m (1, or 2 at half time),
    `rate` = loop speed factor = period_frames / (30 m Q), `start_step` = spacing of the
    candidates' starting loop positions = period_frames / m (at half time a dance beat may also
    start on the music beat in between), `phases` = ceil(30 Q) phases of a motion frame each.
    """
    n = int(np.floor(np.log(MUSIC_PERIOD_MAX_S / MUSIC_PERIOD_MIN_S) / np.log(MUSIC_PERIOD_RATIO))) + 1
    q = MUSIC_PERIOD_MIN_S * MUSIC_PERIOD_RATIO ** np.arange(n)
    m = np.where(q < HALF_TIME_BELOW_S, 2.0, 1.0)
    return {"period_s": q, "beats_per_dance_beat": m,
            "log_prior": -0.5 * (np.log2(60.0 / q / PRIOR_BPM) / PRIOR_OCTAVES) ** 2,
            "rate": period_frames / (C.FPS * m * q), "start_step": period_frames / m,
            "phases": np.ceil(q * C.FPS).astype(int)}


def phase_slots() -> int:
    """Phase columns per tempo in the comb matrix: enough for the longest period."""
    return int(np.ceil(MUSIC_PERIOD_MAX_S * C.FPS))


def onset_times_s() -> np.ndarray:
    """Times the window's onset values are credited to, seconds.

    Onset m (m = 1..156) is the rise from mel frame m - 1 to m. librosa (and choreod's beat
    tracker, whose beats `choreod eval` scores against) credits that rise to frame
    m + n_fft / (2 hop) = m + 2: librosa 0.11 onset.py `onset_strength_multi` pads the flux by
    `lag + n_fft // (2 * hop_length)` frames (dsp/src/onset.rs, "centre compensation").
    Measured on the fixture songs: onset peaks at m * hop / sr fall a median 64 ms before the
    tracked beats; with the shift they coincide.
    """
    return (np.arange(1, C.MUSIC_FRAMES) + C.N_FFT // (2 * C.HOP)) * C.HOP / C.SAMPLE_RATE


def comb_matrix(period_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(156, n_tempi * slots) comb matrix and (n_tempi * slots,) validity of each column.

    Column (i, p) = mean over the teeth p / 30 + j Q_i of a unit-mass Gaussian tooth on the
    onset times; phases p >= ceil(30 Q_i) repeat an earlier phase and are invalid (zero).
    """
    t = onset_times_s()
    slots = phase_slots()
    out = np.zeros((t.size, period_s.size, slots))
    valid = np.zeros((period_s.size, slots), bool)
    for i, q in enumerate(period_s):
        for p in range(int(np.ceil(q * C.FPS))):
            teeth = p / C.FPS + q * np.arange(int((t[-1] - p / C.FPS) / q) + 1)
            teeth = teeth[teeth >= t[0]]
            g = np.exp(-0.5 * ((t[:, None] - teeth[None]) / TOOTH_SIGMA_S) ** 2)
            out[:, i, p] = (g / g.sum(axis=0, keepdims=True)).sum(axis=1) / teeth.size
            valid[i, p] = True
    return out.reshape(t.size, -1), valid.ravel()


def onset_strength(music: np.ndarray) -> np.ndarray:
    """(N, 157, 80) log-mel dB -> (N, 156) onset strength normalised by its window mean."""
    o = np.maximum(np.diff(music.astype(np.float64), axis=1), 0.0).mean(axis=2)
    return o / (o.mean(axis=1, keepdims=True) + ONSET_EPS)


def loop_table(joints: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """(L + 1, 72) normalised features of the loop; row L repeats row 0 (interpolation wraps)."""
    f = (C.joints_to_features(joints.astype(np.float64)) - mean) / std
    return np.concatenate([f, f[:1]])


def warped_candidates(table: np.ndarray, offset: float, step: float, k: int, rate: float,
                      phase: float) -> np.ndarray:
    """(k, 150, 72): the loop at `rate` x speed, loop position offset + step i at motion frame `phase`."""
    n = table.shape[0] - 1
    starts = offset + step * np.arange(k)
    pos = (starts[:, None] + rate * (np.arange(C.WINDOW_FRAMES)[None] - phase)) % n
    lo = np.minimum(np.floor(pos).astype(int), n - 1)
    frac = (pos - lo)[..., None]
    return table[lo] * (1.0 - frac) + table[lo + 1] * frac


def build_graph(table: np.ndarray, k: int, period_frames: float, offset: float, gamma: float):
    """The denoiser as an onnxscript function over constants captured from this scope.

    k = 1 (the sampler oracle) plays the loop at its own speed from beat 0 whatever the music.
    """
    ab = C.alphas_cumprod()
    # Tables computed in float64 and stored as float32 (brief: "compute in float64, store float32").
    sqrt_ab_tab = np.sqrt(ab).astype(np.float32)
    sqrt_1mab_tab = np.sqrt(1.0 - ab).astype(np.float32)
    inv_2var_tab = (1.0 / (2.0 * (1.0 - ab))).astype(np.float32)
    # The data term reads only the frames it weighs: with gamma = 0 the first half, which halves
    # the step's memory and work (the candidates are (N, 72, 10800) floats).
    weighed = C.STRIDE_FRAMES if gamma == 0.0 else C.WINDOW_FRAMES
    frame_w = np.repeat(np.where(np.arange(weighed) < C.STRIDE_FRAMES, 1.0, gamma), C.DIM).astype(np.float32)
    weighed_end = np.array([weighed * C.DIM], np.int64)
    warp = k > 1
    grid = tempo_grid(period_frames)
    comb, valid = comb_matrix(grid["period_s"])
    # Invalid phase columns can never win: their log prior is -1e4 (scores are O(10)).
    prior = np.where(valid, np.repeat(grid["log_prior"], phase_slots()), -1e4)
    if not warp:
        # Every (tempo, phase) scores the same, so ArgMax/TopK take the first (ONNX: ties go to
        # the lowest index), and every tempo plays the loop at its own speed: phase 0, rate 1.
        comb, prior = np.zeros_like(comb), np.zeros_like(prior)
        grid["rate"], grid["start_step"] = np.ones_like(grid["rate"]), np.full_like(grid["rate"], period_frames)
    groups = TEMPO_GROUPS if warp else 1
    n_tempi = grid["period_s"].size
    comb32, prior32 = comb.astype(np.float32), prior.astype(np.float32)
    rate32, step32 = grid["rate"].astype(np.float32), grid["start_step"].astype(np.float32)
    own_step = np.array(period_frames, np.float32)
    tab32 = table.astype(np.float32)                                           # (L + 1, 72)
    loop_len = np.array([table.shape[0] - 1], np.float32)
    last_row = np.array([table.shape[0] - 2], np.int64)
    offset32 = np.array([offset], np.float32)
    index32 = np.arange(k, dtype=np.float32)[None, None, :, None]             # (1, 1, K, 1)
    frames32 = np.arange(C.WINDOW_FRAMES, dtype=np.float32)[None, None, None, :]  # (1, 1, 1, T)
    onset_eps = np.array([ONSET_EPS], np.float32)
    score_eps = np.array([SCORE_EPS], np.float32)
    weight32 = np.array([MUSIC_WEIGHT], np.float32)
    agreement32 = np.array([-TEMPO_AGREEMENT], np.float32)
    grid_shape = np.array([0, n_tempi, phase_slots()], np.int64)
    group_k = np.array([1, groups, k], np.int64)  # Expand broadcasts (N, G, 1) to (N, G, K)
    flat_gk = np.array([0, groups * k, C.WINDOW_FRAMES], np.int64)
    n_groups = np.array([groups], np.int64)
    pool = 2 * TEMPO_PEAK_HALF_WIDTH + 1

    @script()
    def denoiser(x_t: FLOAT["N", 150, 72], t: INT64["N"], music: FLOAT["N", 157, 80],
                 cond: FLOAT["N"]) -> FLOAT["N", 150, 72]:
        axis1 = op.Constant(value_ints=[1])
        axis2 = op.Constant(value_ints=[2])
        sab = op.Gather(op.Constant(value=sqrt_ab_tab), t)         # (N,), t out of 0..999 -> ORT error
        s1mab = op.Gather(op.Constant(value=sqrt_1mab_tab), t)
        inv2v = op.Gather(op.Constant(value=inv_2var_tab), t)

        # Music -> tempo groups: onset strength; log comb score + tempo prior per (tempo, phase);
        # per tempo its best phase; the best local maxima over tempo (TopK).
        rise = op.Relu(op.Sub(op.Slice(music, op.Constant(value_ints=[1]), op.Constant(value_ints=[157]), axis1),
                              op.Slice(music, op.Constant(value_ints=[0]), op.Constant(value_ints=[156]), axis1)))
        onset = op.ReduceMean(rise, axis2, keepdims=0)                            # (N, 156)
        onset = op.Div(onset, op.Add(op.ReduceMean(onset, axis1, keepdims=1), op.Constant(value=onset_eps)))
        comb_score = op.Add(op.MatMul(onset, op.Constant(value=comb32)), op.Constant(value=score_eps))
        score = op.Add(op.Log(comb_score), op.Constant(value=prior32))            # (N, tempi * slots)
        score = op.Reshape(score, op.Constant(value=grid_shape))                  # (N, tempi, slots)
        tempo_score = op.ReduceMax(score, axis2, keepdims=0)                      # (N, tempi)
        best_phase = op.ArgMax(score, axis=2, keepdims=0)                         # (N, tempi)
        pooled = op.MaxPool(op.Unsqueeze(tempo_score, axis1), kernel_shape=[pool],
                            pads=[TEMPO_PEAK_HALF_WIDTH, TEMPO_PEAK_HALF_WIDTH], strides=[1])
        is_peak = op.Equal(tempo_score, op.Squeeze(pooled, axis1))
        peak_score = op.Where(is_peak, tempo_score, op.Constant(value_float=-1e9))
        top, tempo = op.TopK(peak_score, op.Constant(value=n_groups), axis=1)    # (N, G), best first
        behind = op.Sub(top, op.Slice(top, op.Constant(value_ints=[0]), op.Constant(value_ints=[1]), axis1))
        # A tempo more than TEMPO_AGREEMENT behind the best is replaced by the best (a duplicate).
        agree = op.GreaterOrEqual(behind, op.Constant(value=agreement32))       # (N, G)
        tempo = op.Where(agree, tempo, op.Slice(tempo, op.Constant(value_ints=[0]), op.Constant(value_ints=[1]),
                                                 axis1))
        listen = op.Unsqueeze(op.Greater(cond, op.Constant(value_float=0.0)), axis1)  # (N, 1)
        music_logit = op.Where(op.And(listen, agree), op.Mul(op.Constant(value=weight32), behind),
                               op.Constant(value_float=0.0))                     # (N, G)
        r = op.Where(listen, op.Gather(op.Constant(value=rate32), tempo), op.Constant(value_float=1.0))
        p = op.Where(listen, op.Cast(op.GatherElements(best_phase, tempo, axis=1), to=1),
                     op.Constant(value_float=0.0))
        step = op.Where(listen, op.Gather(op.Constant(value=step32), tempo), op.Constant(value=own_step))

        # Candidates (group g, start k): loop position offset + step k + r (f - p), wrapped,
        # linearly interpolated.
        axes23 = op.Constant(value_ints=[2, 3])
        r4, p4, step4 = op.Unsqueeze(r, axes23), op.Unsqueeze(p, axes23), op.Unsqueeze(step, axes23)  # (N, G, 1, 1)
        starts = op.Add(op.Constant(value=offset32), op.Mul(step4, op.Constant(value=index32)))  # (N, G, K, 1)
        pos = op.Add(starts, op.Mul(r4, op.Sub(op.Constant(value=frames32), p4)))              # (N, G, K, T)
        pos = op.Reshape(pos, op.Constant(value=flat_gk))                        # (N, G*K, T)
        length = op.Constant(value=loop_len)
        pos = op.Sub(pos, op.Mul(length, op.Floor(op.Div(pos, length))))         # in [0, L]
        lo = op.Min(op.Cast(op.Floor(pos), to=7), op.Constant(value=last_row))    # int64, <= L - 1
        frac = op.Unsqueeze(op.Sub(pos, op.Cast(lo, to=1)), op.Constant(value_ints=[3]))
        tab = op.Constant(value=tab32)
        g0 = op.Gather(tab, lo)                                                   # (N, G*K, T, 72)
        g1 = op.Gather(tab, op.Add(lo, op.Constant(value_ints=[1])))
        ex = op.Add(g0, op.Mul(frac, op.Sub(g1, g0)))
        ex = op.Reshape(ex, op.Constant(value_ints=[0, 0, -1]))                  # (N, G*K, T*D)
        cand_logit = op.Reshape(op.Expand(op.Unsqueeze(music_logit, axis2), op.Constant(value=group_k)),
                                op.Constant(value_ints=[0, -1]))                 # (N, G*K)

        # Data term: squared distance to each scaled candidate, computed as a difference (not
        # expanded into |x|^2 - 2x.e + |e|^2, which cancels catastrophically in float32 when
        # 1 - ab is ~1e-4 and the logits are ~1e7).
        start, end = op.Constant(value_ints=[0]), op.Constant(value=weighed_end)
        xf = op.Reshape(x_t, op.Constant(value_ints=[0, 1, -1]))                 # (N, 1, T*D)
        sab3 = op.Unsqueeze(sab, op.Constant(value_ints=[1, 2]))                 # (N, 1, 1)
        diff = op.Sub(op.Slice(xf, start, end, axis2), op.Mul(sab3, op.Slice(ex, start, end, axis2)))
        d2 = op.ReduceSum(op.Mul(op.Mul(diff, diff), op.Constant(value=frame_w)), axis2, keepdims=0)
        logits = op.Add(op.Neg(op.Mul(d2, op.Unsqueeze(inv2v, axis1))), cand_logit)   # (N, G*K)
        # Subtract the row max explicitly so exp never overflows whatever ORT's Softmax does.
        logits = op.Sub(logits, op.ReduceMax(logits, axis1, keepdims=1))
        w = op.Softmax(logits, axis=1)
        x0_flat = op.MatMul(op.Unsqueeze(w, axis1), ex)                          # (N, 1, T*D)
        x0 = op.Reshape(x0_flat, op.Shape(x_t))
        pred = op.Div(op.Sub(x_t, op.Mul(sab3, x0)), op.Unsqueeze(s1mab, op.Constant(value_ints=[1, 2])))
        return pred

    return denoiser.to_model_proto()


def choose_warps(music: np.ndarray, period_frames: float) -> list[list[dict[str, float]]]:
    """numpy reference of the graph's music stage: per row of (N, 157, 80) music, its
    TEMPO_GROUPS tempo groups, best first: rate, phase, start_step, period_s, music_logit."""
    grid = tempo_grid(period_frames)
    comb, valid = comb_matrix(grid["period_s"])
    prior = np.where(valid, np.repeat(grid["log_prior"], phase_slots()), -1e4)
    score = (np.log(onset_strength(music) @ comb + SCORE_EPS) + prior).reshape(music.shape[0], -1, phase_slots())
    out = []
    for row in score:
        tempo_score, best_phase = row.max(axis=1), row.argmax(axis=1)
        h = TEMPO_PEAK_HALF_WIDTH
        padded = np.pad(tempo_score, h, constant_values=-np.inf)
        peak = tempo_score == np.array([padded[i:i + 2 * h + 1].max() for i in range(tempo_score.size)])
        order = np.argsort(-np.where(peak, tempo_score, -1e9), kind="stable")[:TEMPO_GROUPS]
        behind = tempo_score[order] - tempo_score[order[0]]
        order = np.where(behind >= -TEMPO_AGREEMENT, order, order[0])
        out.append([{"rate": float(grid["rate"][i]), "phase": float(best_phase[i]),
                     "start_step": float(grid["start_step"][i]), "period_s": float(grid["period_s"][i]),
                     "music_logit": float(MUSIC_WEIGHT * (tempo_score[i] - tempo_score[order[0]]))}
                    for i in order])
    return out


def description(k: int, gamma: float, warp: bool) -> str:
    half = ("from the window's first half (frames 0-74)" if gamma == 0.0 else
            f"with the second half weighted {gamma:g}")
    music = (f"Music conditioning (beat warp): from the window's log-mel, onset strength is matched against combs of "
             f"60-180 BPM and every phase; for each of the {TEMPO_GROUPS} best tempi (within {TEMPO_AGREEMENT:g} of "
             f"the best log score) the loop is played at the speed and phase that put its kinematic beats on the "
             f"comb's teeth (every second tooth below {HALF_TIME_BELOW_S:g} s); logit += {MUSIC_WEIGHT:g} x (tempo "
             "score - best). cond = 0 plays the loop at its own tempo." if warp else
             "No music conditioning (one candidate: the sampler oracle, the loop at its own tempo).")
    return (
        f"Closed-form denoiser over K={k} windows per tempo read from a loop of the AIST++ motion "
        "gBR_sBM_cAll_d04_mBR0_ch01 (CC BY 4.0, AIST++ / AIST Dance DB), each starting on a kinematic beat "
        "(or half beat): x0_hat = softmax-weighted mean of the candidates, weights = Gaussian posterior given "
        f"x_t and t computed {half}; epsilon follows. {music} With K=1 every correct sampler returns that "
        "candidate."
    )


def readme_text(k: int, loop_frames: int, gamma: float, period: float, offset: float, warp: bool) -> str:
    rate = tempo_grid(period)["rate"]
    oracle = ("\n**This build holds one candidate (`--exemplars 1`): the music stage is off and every correct "
              "sampler returns the loop from its first beat at its own tempo (the sampler oracle).**\n"
              if not warp else "")
    return f"""# `exemplar` — the closed-form denoiser over a real AIST++ dance, retimed onto the beat

Built by `models/packages/build.py exemplar --exemplars {k}` from
`models/packages/exemplar-source/{SOURCE_NPY}` (see the README there for provenance and licence:
AIST++ annotations, CC BY 4.0 — credit AIST++ (Li et al., ICCV 2021) and the AIST Dance Video DB).
{oracle}
## In plain words

The package knows one real dance: a {loop_frames / C.FPS:g} s loop of an AIST++ break routine. It moves
on a regular beat: its kinematic beats (the moments the body's joints slow down most, found
as Bailando's beat-alignment code finds them) come every {period:g} frames ({period / C.FPS:g} s,
{60 * C.FPS / period:g} BPM), {loop_frames / period:g} per loop. For each 5 s window of a song the network
listens for where the song's onsets (sudden rises in loudness across the mel bands) fall, finds
the regular pulses that fit them best (at most {TEMPO_GROUPS}, nearly as good as the best), and plays the
dance faster or slower (x{rate.min():.3f} to x{rate.max():.3f}) and shifted so that the dance's beats land on
the pulse: on every beat of songs slower than {60 / HALF_TIME_BELOW_S:g} BPM, on every second beat of faster
ones (a dance played much faster than its own tempo slides its feet). The diffusion then chooses
which pulse and which beat of the dance the window starts on; a window whose predecessor's pulse
is among its own continues it seamlessly. Nothing but the timing is changed: the motion is the
real dance, replayed at another tempo.

## What the network computes

Loop table: the {loop_frames} frames of the loop retimed so that kinematic beat j sits exactly at frame
{offset:.4f} + {period:g} j (a piecewise-linear time map through the measured beats, linear interpolation;
beats move by at most 1.25 frames), in the contract representation (root xyz, then joints 1..23
minus the root; metres, y-up, floor at y = 0), normalised with the package's mean/std (over the
loop's frames; std floored at {STD_FLOOR} m); one more row repeats frame 0.

From the music of the window (log-mel dB, 157 x 80) only (choreod runs this part once per
batch of windows, not at every denoising step):

    onset[m]  = mean_b max(0, mel[m, b] - mel[m-1, b]),  m = 1..156, credited to (m + 2) * 32 ms
    onset    /= mean(onset) + {ONSET_EPS:g}
    score[Q, p] = ln(mean of onset at the teeth p / 30 + j Q  +  {SCORE_EPS:g}) - 0.5 (log2(60 / Q / {PRIOR_BPM:g}) / {PRIOR_OCTAVES:g})^2

(m + 2: librosa's onset_strength, and so choreod's beat tracker, credits the rise from frame
m - 1 to m to frame m + n_fft / (2 hop).) Q runs over {MUSIC_PERIOD_MIN_S:.4f}..{MUSIC_PERIOD_MAX_S:g} s in {(MUSIC_PERIOD_RATIO - 1) * 100:g} % steps, p over
0..ceil(30 Q)-1 motion frames; each tooth is a unit-mass Gaussian (sigma {TOOTH_SIGMA_S * 1000:g} ms) over the
onset times; the prior is choreod's beat tracker's (librosa's: 120 BPM, one octave). Per Q its
best phase p(Q) and score s(Q); the {TEMPO_GROUPS} largest local maxima of s over +-{TEMPO_PEAK_HALF_WIDTH} steps are the
tempo groups g, best first; a group more than {TEMPO_AGREEMENT:g} behind the best is replaced by the best.
Group g plays the loop at

    m_g = 2 if Q_g < {HALF_TIME_BELOW_S:g} s else 1            (music beats per dance beat)
    r_g = {period:g} / (30 m_g Q_g)                       (loop frames per motion frame)

Candidates, group g, k = 0..K-1, f = 0..149 (motion frames):

    pos(f) = ({offset:.4f} + ({period:g} / m_g) k + r_g (f - p(Q_g))) mod {loop_frames}    (loop frames)
    e[f]   = linear interpolation of the loop table at pos(f)

so a kinematic beat of the loop sits at motion frame p(Q_g) and every m_g Q_g seconds after it.
cond = 0 (the unconditional row): every group is r = 1, p = 0, m = 1 (no music at all).

Given normalised x_t and the training step t (alphas_cumprod ab_t of the linear schedule
1e-4 -> 0.02 over 1000 steps, computed in float64, stored as float32 tables gathered by t):

    d2_i    = sum_f c_f ||x_t[f] - sqrt(ab_t) e_i[f]||^2,  c_f = 1 for f < 75, {gamma:g} for f >= 75
    logit_i = -d2_i / (2 (1 - ab_t)) + {MUSIC_WEIGHT:g} (s(Q_g(i)) - s(Q_best))
    w = softmax(logit),   x0_hat = sum_i w_i e_i
    pred = eps = (x_t - sqrt(ab_t) x0_hat) / sqrt(1 - ab_t)

This is the posterior mean of x0 given the first half of x_t when x0 is drawn from the
candidates with those weights (the first 75 frames identify the candidate), so a correct sampler
returns one candidate: real dance motion, retimed. Weighting only the first half makes each
window continue the one before it under EDGE's long-form sampler, which copies window i's second
half into window i+1's first half at every step: when window i+1 offers window i's pulse (same
tempo, beats on the same grid) the continuation is exactly one of its candidates; otherwise the
stitcher cross-fades. With K = 1 the package ignores the music and every correct sampler returns
that one window for any noise: the oracle for sampler tests.

The manifest sets `set_alpha_to_one = true`: DDIM's last step then returns x0_hat, a candidate,
instead of stopping at the noise level of alphas_cumprod[0]; and `eta = 1` (as EDGE samples).

## What it gives (BENCHMARKS.md, "eval", for the numbers and the command)

`bas_music_beats` (Bailando's convention at 60 fps, what `choreod eval X.h5 --music SONG`
prints; mean of seeds 0-3) rose from 0.18 to 0.336 on vibe_ace (the song the constants were
chosen on), from 0.17 to 0.244 on hungarian_dance_5 (held out) and from 0.04-0.33 to 0.46-0.93
on synthetic drum patterns of 60-180 BPM. On six held-out real songs (`scripts/bench-dance-beats`
with BENCH_HELDOUT_EXTRA) it averages 0.390: 0.43-0.48 on four, 0.244 and 0.239 on a rubato
string piece and a shuffle, whose 5 s windows favour a pulse at 3:2 or 4:3 of the tracked beat.
`choreod dance` pins planted feet before its rigid fit
(`choreo_datasets::lock_feet`: the package's windows barely skate, the cross-fades between
windows that disagree did), so the dance's foot skating is 0.00-0.0104 (0-0.8x the AIST++ fixture
motion's own 0.0126; it was 2.2-2.7x before the beat warp) and its PFC 0.07-0.19 (0.15-0.40x
the fixture's 0.466).

## Limits

- One routine: every song gets the same dance, at another speed and phase.
- The pulse is found per 5 s window from onsets only: songs without clear onsets (soft strings,
  rubato) get a weak or wrong pulse, and a window may pick a pulse at 2/3 or 3/2 of the beat.
- Above {60 / HALF_TIME_BELOW_S:g} BPM the dance meets every second beat only, which caps the
  music-beat BAS near 0.5.

## Files

- `denoiser.onnx`: opset 18, inputs x_t [N,150,72] f32, t [N] i64, music [N,157,80] f32,
  cond [N] f32; output pred [N,150,72] f32 (epsilon).
- `choreod-model.toml`: manifest (mean/std, schedule, sampler defaults, sha256 of the ONNX file).

Checked by `build.py check models/packages/exemplar` (onnxruntime, N = 1 and 4; the graph's
candidates against the numpy reference in pkg_exemplar.py for three click tracks and random
music; on the click tracks the candidates' kinematic beats meet the clicks).
"""


def n_candidates(loop_frames: int, period: float) -> int:
    """Two candidates per kinematic beat of the loop: starting on a beat, or half a beat later."""
    return 2 * round(loop_frames / period)


def build(out_dir: Path, source_npy: Path, k: int | None, gamma: float = SECOND_HALF_WEIGHT) -> int:
    joints = np.load(source_npy, allow_pickle=False)
    if joints.ndim != 3 or joints.shape[1:] != (C.N_JOINTS, 3) or joints.shape[0] < C.WINDOW_FRAMES:
        raise SystemExit(f"{source_npy}: expected a loop of joints (T >= {C.WINDOW_FRAMES}, 24, 3), got {joints.shape}")
    period, offset = beat_grid(joints)
    k_max = n_candidates(joints.shape[0], period)
    k = k_max if k is None else k
    if not 1 <= k <= k_max:
        raise SystemExit(f"--exemplars must be in 1..{k_max} (two per kinematic beat of the loop), got {k}")
    joints = retime_to_grid(joints, period, offset)
    frames = C.joints_to_features(joints)
    # float64 accumulation over the loop's frames, stored float32
    mean = frames.mean(axis=0).astype(np.float32)
    std = np.maximum(frames.std(axis=0), STD_FLOOR).astype(np.float32)
    table = loop_table(joints, mean.astype(np.float64), std.astype(np.float64))
    warp = k > 1
    model = build_graph(table, k, period, offset, gamma)
    model.doc_string = description(k, gamma, warp)
    out_dir.mkdir(parents=True, exist_ok=True)
    sha = C.save_model(model, out_dir / "denoiser.onnx")
    C.write_manifest(out_dir, name="exemplar", description=description(k, gamma, warp), mean=mean, std=std,
                     onnx_file="denoiser.onnx", onnx_sha256=sha, eta=SAMPLER_ETA,
                     set_alpha_to_one=SET_ALPHA_TO_ONE)
    (out_dir / "README.md").write_text(readme_text(k, joints.shape[0], gamma, period, offset, warp),
                                       encoding="utf-8")
    return k
