"""The measures of scripts/bench-library (issue 24): run through that wrapper, which builds the
release binary and passes its path in $CHOREOD.

Per song (60 s excerpt) and seed, `choreod dance` then `choreod eval --music --json`; then, from
the written joints (numpy, vectorised):
- pose overlap between songs: for songs A != B and each seed s, the share of the frames of A's
  dance (seed s) whose nearest pose in B's dance (seed s) lies within 3 cm mean joint distance,
  poses root-relative (the root joint subtracted) and facing aligned (each pose turned about y
  so that its left-hip -> right-hip vector points along +x); the mean over seeds fills the
  matrix, whose off-diagonal median is the headline. For reference the same share between two
  seeds of the same song (all ordered seed pairs).
- BAS, PFC, skating: `choreod eval` (bas_music_beats, Bailando's convention; pfc, skate_ratio),
  PFC and skating also as ratios to the AIST++ fixture motion's own (`choreod eval FIXTURE.pkl`).
- largest bone turn between consecutive frames at 30 fps: the angle between a bone's directions
  (child joint minus parent joint, the file's `parents`) in frames t and t+1, the largest over
  bones and frames; and how many frames turn any bone by more than 60 degrees.
- reaction to a change (the offline peer of `scripts/bench-live --click`): three synthetic
  61 s songs per seed, danced with the same seed: `change`, a quiet 90 BPM click track (A) that
  turns at CHANGE_S (31 s, off the 2.5 s window grid) into a loud 160 BPM one with hi-hats (B);
  `steady`, A throughout (the control: an A -> A splice, i.e. no change); `fast`, B throughout
  (how the package dances the new music). Each dance is cut into 2.5 s windows (the sampler's
  stride) on a grid from the change: 4 before, 10 after. Per window the dance's character:
  energy (mean joint speed, m/s) and kinematic-beat tempo (60 s over the median interval of the
  window's kinematic beats: minima of the Gaussian-smoothed joint speed, Bailando's beats). A
  character can show the change only if the `fast` dance's level after the change (median over
  its windows) differs by >= 1.25x from the `change` dance's own level before (median of its
  4 windows before); a window has moved when, in such a character, it has left its own dance's
  level before the change by >= 1.25x, towards (nearer, in log) the `fast` dance's level. The
  reaction is the first moved window of `change` (1 = the 2.5 s right after the change; target
  <= 2); the control is the `steady` dance's windows after 31 s judged the same way against its
  own level before: none may move, else the measure says nothing. Why not compare `change` with
  `steady` pose by pose (the measure of session 10): the two dances differ before the change
  already, although their music is the same there, because the dance pipeline analyses the
  whole song: the log-mel's top_db floor is max - 80 dB over the whole signal, so the loud
  second half lifts the floor under the quiet first half's clicks (measured with `choreod mel`:
  the first 30 s differ by up to 27 dB, floor -81 -> -54 dB), and `choreod beats` finds no beat
  before 31 s in the spliced song (in the A-only song: 90 BPM beats from 2.3 s). A valid control
  must therefore compare each dance with itself; `before_level_vs_a_only` reports, per seed, how
  differently the same first 31 s of music are danced in the two songs.
"""

import argparse
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import wave
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import argrelmin

ROOT = Path(__file__).resolve().parent.parent
CHOREOD = os.environ.get("CHOREOD", str(ROOT / "target/release/choreod"))
SHARED = ROOT.parent / "shared"
FIXTURE = SHARED / "fixtures/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"
CACHE = ROOT / "target/bench/library-songs"
EXCERPT_S = 60.0
# Pose overlap: the threshold (mean joint distance, metres).
NEAR_M = 0.03
# Bone turn bar of the issue (degrees per frame at 30 fps).
TURN_BAR_DEG = 60.0
# The reaction measure: the change's moment (not on the 2.5 s window grid), the window stride.
CHANGE_S = 31.0
STRIDE_S = 2.5
REACTION_BEFORE, REACTION_AFTER = 4, 10
CHARACTERS = ("energy", "tempo")
# The two musics' dances must differ by this factor in a character for it to show a change.
SEPARATES = 1.25
# Smoothing of the speed curve before its minima are taken as kinematic beats: Bailando's
# Gaussian of sigma 5 frames (beat_align_score.py; datasets/src/metrics/beats.rs) taken at
# AIST++'s 60 fps, so that a 30 fps dance is smoothed over the same time.
KINEMATIC_SIGMA_S = 5 / 60

# Debian game music (bookworm). path: inside the package; sha256: of that file; offset: where
# the 60 s excerpt starts (past the intro). Licences from each package's debian/copyright
# ("Files: *"); authors from the package's own credits where it has them.
DEBIAN = {
    "hedgewars-data": ("1.0.2-6", "GPL-2 (hedgewars-data debian/copyright)"),
    "wesnoth-1.16-music": ("1:1.16.9-1", "GPL-2+ (wesnoth-1.16-music debian/copyright)"),
    "frozen-bubble-data": ("2.212-11", "GPL-2 (frozen-bubble-data debian/copyright)"),
}
HW = "usr/share/games/hedgewars/Data/Music/"
SONGS = [
    # name, character, source (Debian package or "committed"), path, sha256, offset s, author
    ("olympics_sd", "slow (about 70 BPM)", "hedgewars-data", HW + "olympics_sd.ogg",
     "c4150c4ebbf53dda685cdf191fa6eba79dcc2e6fc9acf5faedebb59c29d55a69", 20.0,
     "yd (opengameart.org), per hedgewars Music/credits.txt"),
    ("snow", "calm, under 90 BPM", "hedgewars-data", HW + "snow.ogg",
     "5823f31293d3e90de12a5562672722abd4327d548db7ce0eced82744711c3856", 30.0,
     "Jonatan Nilsson, per hedgewars Music/credits.txt"),
    ("Rock", "mid-tempo rock", "hedgewars-data", HW + "Rock.ogg",
     "3208addeb10bde065881b6468ed44818deefcec4409547685e7f9b4aff94f814", 30.0,
     "HSR, per hedgewars Music/credits.txt"),
    ("City", "swing (off-beats at 2/3 of the beat)", "hedgewars-data", HW + "City.ogg",
     "58b71f8e750a9d3686c2ea61b24d63e3a9becd840d32067ecb098792998d497b", 30.0,
     "HSR, per hedgewars Music/credits.txt"),
    ("frozen-mainzik-1p", "fast electronic (about 170 BPM)", "frozen-bubble-data",
     "usr/share/games/frozen-bubble/snd/frozen-mainzik-1p.ogg",
     "7704fcd44eda9f6fa47e6da4232ebf961c19919abf9964f07320ed7f21f5d7c2", 30.0,
     "The Frozen-Bubble Team"),
    ("heroes_rite", "orchestral", "wesnoth-1.16-music",
     "usr/share/games/wesnoth/1.16/data/core/music/heroes_rite.ogg",
     "e35cc04e15528a0b9f1619048f72a06567374d87f51122db82e4417a2bf08f4a", 30.0,
     "Battle for Wesnoth"),
    ("Lets_Go_Fishin", "shuffle (117 BPM)", "committed",
     "tests/fixtures/heldout/Karissa_Hobbs_-_Lets_Go_Fishin.ogg",
     "27b3667c396c1831511aa3c415fcf582b6e8be560cafb844c5b67b76b72c1cb3", 20.0,
     "Karissa Hobbs, CC BY 3.0 (tests/fixtures/heldout/LICENSES.md)"),
    ("Sugar_Plum_Fairy", "orchestral arrangement, celesta (110 BPM)", "committed",
     "tests/fixtures/heldout/Kevin_MacLeod_-_P_I_Tchaikovsky_Dance_of_the_Sugar_Plum_Fairy.ogg",
     "b5c1a3e26310e6618d3c124f458654cd235650fcb9db7d711302644566600484", 20.0,
     "Kevin MacLeod, CC BY 3.0 (tests/fixtures/heldout/LICENSES.md)"),
]
# The contact sheets: three songs of different character.
PICTURE_SONGS = ("olympics_sd", "frozen-mainzik-1p", "heroes_rite")


def say(msg):
    print(msg, file=sys.stderr, flush=True)


def fail(msg):
    say(f"bench-library: {msg}")
    sys.exit(1)


def run(args, **kw):
    """Run a command; on failure stop with its stderr."""
    p = subprocess.run([str(a) for a in args], capture_output=True, text=True, **kw)
    if p.returncode != 0:
        fail(f"`{' '.join(str(a) for a in args)}` failed ({p.returncode}):\n{p.stderr.strip()}")
    return p.stdout


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fetch_songs():
    """Every held-out song's full source file, checked against its pinned sha256."""
    src = CACHE / "src"
    src.mkdir(parents=True, exist_ok=True)
    out = {}
    missing = {}
    for name, _, pkg, path, digest, _, _ in SONGS:
        if pkg == "committed":
            out[name] = ROOT / path
        else:
            out[name] = src / Path(path).name
            if not (out[name].exists() and sha256(out[name]) == digest):
                missing.setdefault(pkg, []).append(path)
    for pkg, paths in missing.items():
        version, _ = DEBIAN[pkg]
        say(f"fetching {pkg}={version} (apt-get download; nothing is installed)")
        with tempfile.TemporaryDirectory(dir=CACHE) as tmp:
            p = subprocess.run(["apt-get", "download", f"{pkg}={version}"], cwd=tmp,
                               capture_output=True, text=True)
            if p.returncode != 0:
                fail(f"apt-get download {pkg}={version} failed: {p.stderr.strip()}\n"
                     f"  (run `apt-get update` first; if bookworm no longer has this version, "
                     f"the pinned sha256 below decides whether another one may be used)")
            deb = next(Path(tmp).glob("*.deb"))
            run(["dpkg", "-x", deb, Path(tmp) / "x"])
            for path in paths:
                shutil.copyfile(Path(tmp) / "x" / path, src / Path(path).name)
    for name, _, pkg, path, digest, _, _ in SONGS:
        got = sha256(out[name])
        if got != digest:
            fail(f"{out[name]}: sha256 {got}, pinned {digest} ({pkg} {path})")
    return out


def cut_excerpts(sources):
    """60 s excerpts at the songs' fixed offsets (sox; 16-bit WAV at the source's rate)."""
    exc = CACHE / "excerpts"
    exc.mkdir(parents=True, exist_ok=True)
    out = {}
    for name, _, _, _, _, offset, _ in SONGS:
        out[name] = exc / f"{name}.wav"
        if not out[name].exists():
            tmp = exc / f".{name}.tmp.wav"
            run(["sox", sources[name], "-b", "16", tmp, "trim", offset, EXCERPT_S])
            tmp.rename(out[name])
    return out


def write_wav(path, y, sr):
    pcm = (np.clip(y, -1, 1) * 32767).astype("<i2")
    with wave.open(str(path), "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(sr)
        w.writeframes(pcm.tobytes())


def click_songs(work):
    """A: 90 BPM, quiet (clicks peaking at -30 dBFS); B: 160 BPM, loud (-3 dBFS), with hi-hats
    on the eighths. 61 s each: `change` is A until CHANGE_S, then B; `steady` is A throughout
    (the control: the A -> A splice); `fast` is B throughout (the new music's dance)."""
    sr = 22050
    n = int(61 * sr)
    rng = np.random.default_rng(24)
    tk = np.arange(int(0.08 * sr)) / sr
    click = np.sin(2 * np.pi * 1000 * tk) * np.exp(-tk / 0.01) + \
        np.sin(2 * np.pi * 80 * tk) * np.exp(-tk / 0.03)
    click /= np.abs(click).max()
    th = np.arange(int(0.03 * sr)) / sr
    hat = rng.standard_normal(th.size) * np.exp(-th / 0.008)
    hat /= np.abs(hat).max()

    def track(bpm, gain, start, end, hats):
        y = np.zeros(n)
        beat = 60.0 / bpm
        t = start
        while t < end:
            i = int(round(t * sr))
            m = min(click.size, n - i)
            y[i:i + m] += gain * click[:m]
            if hats:
                j = int(round((t + beat / 2) * sr))
                m = max(0, min(hat.size, n - j))
                y[j:j + m] += 0.3 * gain * hat[:m]
            t += beat
        return y

    quiet, loud = 10 ** (-30 / 20), 10 ** (-3 / 20)
    change = track(90, quiet, 0.25, CHANGE_S, False) + track(160, loud, CHANGE_S, 61, True)
    steady = track(90, quiet, 0.25, 61, False)
    fast = track(160, loud, 0.25, 61, True)
    paths = {"change": work / "click_90quiet_then_160loud.wav", "steady": work / "click_90quiet.wav",
             "fast": work / "click_160loud.wav"}
    for key, y in (("change", change), ("steady", steady), ("fast", fast)):
        write_wav(paths[key], y, sr)
    return paths


def read_dance(path):
    with h5py.File(path, "r") as f:
        joints = f["motion/joints"][:].astype(np.float64)
        m = f["motion"].attrs
        prov = dict(f["provenance"].attrs) if "provenance" in f else {}
        return {
            "joints": joints,
            "fps": float(m["fps"]),
            "parents": np.asarray(m["parents"], dtype=int),
            "names": [str(n) for n in m["joint_names"]],
            "model": str(prov.get("model_name", "?")),
            "model_sha256": str(prov.get("model_sha256", "?")),
        }


def at_30fps(joints, fps):
    """Positions at 30 fps: every k-th frame for an integer multiple, else linear resampling."""
    if abs(fps - 30.0) < 1e-6:
        return joints
    k = fps / 30.0
    if abs(k - round(k)) < 1e-6:
        return joints[::round(k)]
    t = np.arange(0, (len(joints) - 1) / fps, 1 / 30.0)
    src = np.arange(len(joints)) / fps
    flat = joints.reshape(len(joints), -1)
    return np.stack([np.interp(t, src, flat[:, c]) for c in range(flat.shape[1])], 1).reshape(
        len(t), *joints.shape[1:])


def poses(joints):
    """Root-relative, facing-aligned poses (T, J, 3): the root joint subtracted, then each
    frame turned about y so its left-hip (1) -> right-hip (2) vector points along +x."""
    rel = joints - joints[:, :1]
    v = rel[:, 2] - rel[:, 1]
    th = np.arctan2(v[:, 2], v[:, 0])[:, None]
    c, s = np.cos(th), np.sin(th)
    x, y, z = rel[..., 0], rel[..., 1], rel[..., 2]
    return np.stack([x * c + z * s, y, -x * s + z * c], -1)


def nearest_mean_joint_distance(a, b, chunk=384):
    """For every pose of a (Ta, J, 3), the smallest mean joint distance to any pose of b: the
    exhaustive computation the pruned one below is checked against in every run."""
    out = np.empty(len(a))
    b_sq = (b * b).sum(-1)  # (Tb, J)
    for i in range(0, len(a), chunk):
        ac = a[i:i + chunk]
        a_sq = (ac * ac).sum(-1)
        total = np.zeros((len(ac), len(b)))
        for j in range(a.shape[1]):
            d2 = a_sq[:, j, None] + b_sq[None, :, j] - 2.0 * ac[:, j] @ b[:, j].T
            total += np.sqrt(np.maximum(d2, 0.0))
        out[i:i + chunk] = total.min(1) / a.shape[1]
    return out


# Joints whose exact distances make the lower bound of the pruned overlap (SMPL-24: ankles,
# head, elbows, wrists): they move most, so the bound excludes most far pairs at once.
BOUND_JOINTS = (7, 8, 15, 18, 19, 20, 21)
# Slack on the bounds (metres) so that rounding can never decide a pair the exact test would not.
BOUND_SLACK = 1e-9


def near_both_ways(a, b, chunk=200_000):
    """Which poses of a have a pose of b within NEAR_M mean joint distance, and which poses of b
    have one of a: the same booleans as thresholding nearest_mean_joint_distance both ways, but
    one pass over the pairs and most pairs decided by bounds. With d_j the joint distances and
    F = sqrt(sum d_j^2) (one matrix product for all pairs): mean d_j <= F / sqrt(J) (so a pair is
    near when F <= NEAR_M sqrt(J)), and sum d_j >= sum_S d_j + sqrt(F^2 - sum_S d_j^2) for the
    exact distances of the joints S (the rest's sum is at least their root sum of squares), so a
    pair above NEAR_M by that bound is far. Only the pairs left are measured exactly."""
    J = a.shape[1]
    fa, fb = a.reshape(len(a), -1), b.reshape(len(b), -1)
    f2 = np.maximum((fa * fa).sum(1)[:, None] + (fb * fb).sum(1)[None] - 2.0 * fa @ fb.T, 0.0)
    near = f2 <= (NEAR_M * np.sqrt(J) - BOUND_SLACK) ** 2
    part, part2 = np.zeros_like(f2), np.zeros_like(f2)
    for j in BOUND_JOINTS:
        d2 = np.maximum((a[:, j] ** 2).sum(1)[:, None] + (b[:, j] ** 2).sum(1)[None]
                        - 2.0 * a[:, j] @ b[:, j].T, 0.0)
        part += np.sqrt(d2)
        part2 += d2
    lower = (part + np.sqrt(np.maximum(f2 - part2, 0.0))) / J
    open_ = (lower <= NEAR_M + BOUND_SLACK) & ~near
    a_near, b_near = near.any(1), near.any(0)
    # Only pairs that could still decide a pose not yet known to be near.
    open_ &= ~a_near[:, None] | ~b_near[None, :]
    ia, ib = np.nonzero(open_)
    for k in range(0, len(ia), chunk):
        x, y = ia[k:k + chunk], ib[k:k + chunk]
        hit = np.linalg.norm(a[x] - b[y], axis=-1).mean(1) <= NEAR_M
        a_near[x[hit]] = True
        b_near[y[hit]] = True
    return a_near, b_near


def check_overlap(a, b, label):
    """The pruned overlap against the exhaustive one on one pair of dances, both ways: the same
    booleans or the run stops; the two times."""
    t0 = time.monotonic()
    exhaustive = (nearest_mean_joint_distance(a, b) <= NEAR_M,
                  nearest_mean_joint_distance(b, a) <= NEAR_M)
    t1 = time.monotonic()
    pruned = near_both_ways(a, b)
    t2 = time.monotonic()
    for x, y in zip(exhaustive, pruned):
        if not np.array_equal(x, y):
            fail(f"pruned pose overlap differs from the exhaustive one on {label}: "
                 f"{int((x != y).sum())} frames")
    return {"pair": label, "frames_near": [int(x.sum()) for x in exhaustive],
            "exhaustive_s": t1 - t0, "pruned_s": t2 - t1}


def shares_both_ways(a, b):
    a_near, b_near = near_both_ways(a, b)
    return float(a_near.mean()), float(b_near.mean())


def bone_turns(joints, parents):
    """Per frame pair and bone: the angle (degrees) between the bone's directions."""
    bones = [j for j in range(len(parents)) if parents[j] >= 0]
    u = joints[:, bones] - joints[:, parents[bones]]
    u /= np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-12)
    cos = np.clip((u[1:] * u[:-1]).sum(-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos)), bones


def turn_summary(joints, fps, parents, names):
    ang, bones = bone_turns(at_30fps(joints, fps), parents)
    t, b = np.unravel_index(np.argmax(ang), ang.shape)
    return {
        "max_deg": float(ang[t, b]),
        "bone": names[bones[b]],
        "frame": int(t + 1),
        "frames_over_bar": int((ang.max(1) > TURN_BAR_DEG).sum()),
    }


def dance(song, out, seed, model):
    args = [CHOREOD, "dance", song, "-o", out, "--seed", seed]
    if model:
        args += ["--model", model]
    env = {k: v for k, v in os.environ.items() if k != "CHOREOD_MODEL"}
    run(args, env=env)


def eval_json(path, music=None):
    args = [CHOREOD, "eval", path, "--json"] + (["--music", music] if music else [])
    return json.loads(run(args))["generated"][0]


def tempo(song):
    return float(json.loads(run([CHOREOD, "beats", song, "--json"]))["tempo_bpm"])


def speed_curve(joints, fps):
    """Per frame step: the mean joint speed (m/s) between frames t and t+1."""
    return np.linalg.norm(np.diff(joints, axis=0), axis=-1).mean(1) * fps


def kinematic_beats(speed, fps):
    """Frames of the dance's kinematic beats: local minima of the mean joint speed smoothed by a
    Gaussian of KINEMATIC_SIGMA_S (Bailando's motion beats, as BAS uses them)."""
    smooth = gaussian_filter1d(speed, KINEMATIC_SIGMA_S * fps)
    return argrelmin(smooth)[0]


def window_character(dance_, starts):
    """Per window (start times in s, STRIDE_S long): the dance's energy (mean joint speed, m/s)
    and its kinematic-beat tempo (60 s over the median interval between the window's kinematic
    beats; NaN with fewer than two)."""
    fps = dance_["fps"]
    speed = speed_curve(dance_["joints"], fps)
    beats = kinematic_beats(speed, fps)
    out = []
    for lo in starts:
        f0, f1 = int(round(lo * fps)), int(round((lo + STRIDE_S) * fps))
        inside = beats[(beats >= f0) & (beats < f1)]
        tempo = 60.0 * fps / float(np.median(np.diff(inside))) if len(inside) > 1 else float("nan")
        out.append({"energy": float(speed[f0:f1].mean()), "tempo": tempo})
    return out


def reaction(work, seeds, model):
    """The click -> reaction measure (see the module docstring): per seed, the character of the
    spliced song's dance per window, against the levels of the A-only (steady) and B-only (fast)
    dances after the change; the steady dance's own windows are the control."""
    clicks = click_songs(work)
    before = [CHANGE_S + k * STRIDE_S for k in range(-REACTION_BEFORE, 0)]
    after = [CHANGE_S + k * STRIDE_S for k in range(REACTION_AFTER)]
    labels = list(range(-REACTION_BEFORE, 0)) + list(range(1, REACTION_AFTER + 1))
    per_seed = []
    for s in range(seeds):
        d = {}
        for key, path in clicks.items():
            out = work / f"click_{key}_s{s}.h5"
            say(f"  reaction: dancing {path.name} seed {s}")
            dance(path, out, s, model)
            d[key] = read_dance(out)
        ch = {key: window_character(d[key], before + after) for key in clicks}
        n_before = len(before)
        # Each dance's own level before the change; the new music's: the B-only dance's after.
        own = {key: {c: float(np.nanmedian([w[c] for w in ch[key][:n_before]]))
                     for c in CHARACTERS} for key in ("change", "steady")}
        target = {c: float(np.nanmedian([w[c] for w in ch["fast"][n_before:]])) for c in CHARACTERS}
        # A character can show the change only where the new music's dance differs in it from
        # the spliced dance before the change.
        separates = [c for c in CHARACTERS
                     if abs(np.log(target[c] / own["change"][c])) >= np.log(SEPARATES)]

        def moved(key, w):
            """The characters in which a window has left its dance's level before the change by
            SEPARATES or more, towards the new music's level (nearer it, in log)."""
            return [c for c in separates if np.isfinite(w[c]) and
                    abs(np.log(w[c] / own[key][c])) >= np.log(SEPARATES) and
                    abs(np.log(w[c] / target[c])) < abs(np.log(w[c] / own[key][c]))]

        windows = {key: [{"window": k, "start_s": lo, **w, "moved": moved(key, w)}
                         for k, lo, w in zip(labels, before + after, ch[key])]
                   for key in ("change", "steady")}
        first = next((w["window"] for w in windows["change"] if w["window"] > 0 and w["moved"]),
                     None)
        per_seed.append({
            "seed": s, "levels_before": own, "level_new_music": target, "separating": separates,
            "first_moved_window": first if separates else None,
            "after_windows_moved": sum(bool(w["moved"]) for w in windows["change"]
                                       if w["window"] > 0),
            "control_windows_moved": sum(bool(w["moved"]) for w in windows["steady"]
                                         if w["window"] > 0),
            "before_windows_moved": sum(bool(w["moved"]) for w in windows["change"]
                                        if w["window"] < 0),
            # How the same seconds of the same music are danced in the two songs (whole-song
            # analysis shows here): the spliced dance's level before / the A-only dance's.
            "before_level_vs_a_only": {c: own["change"][c] / own["steady"][c] for c in CHARACTERS},
            "windows": windows,
        })
    return per_seed


def contact_sheets(dances, pictures, label, tempos):
    """Seed-0 contact sheets (`choreod render`, 12 frames over the dance) of three songs side by
    side, one column per song with its name above, the package named at the top; a palette PNG."""
    pictures.mkdir(parents=True, exist_ok=True)
    font = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf"
    tiles = []
    for name in PICTURE_SONGS:
        sheet = pictures / f".{name}.png"
        run([CHOREOD, "render", dances[(name, 0)], "-o", sheet, "--width", "120", "--height", "120"])
        tiles.append(sheet)
    character = {s[0]: s[1] for s in SONGS}
    inputs, parts = [], []
    for i, (name, sheet) in enumerate(zip(PICTURE_SONGS, tiles)):
        inputs += ["-i", str(sheet)]
        text = f"{name} - {character[name]}, tracked {tempos[name]:.0f} BPM".replace(":", r"\:")
        parts.append(f"[{i}:v]pad=iw+16:ih+34:8:30:white,"
                     f"drawtext=fontfile={font}:text='{text}':x=10:y=9:fontsize=13:fontcolor=black"
                     f"[c{i}]")
    n = len(tiles)
    head = f"choreod dance, package '{label}', seed 0: 12 frames over each 60 s excerpt"
    head = head.replace(":", r"\:")
    graph = ";".join(parts) + ";" + "".join(f"[c{i}]" for i in range(n)) + \
        f"hstack=inputs={n},pad=iw:ih+30:0:30:white," \
        f"drawtext=fontfile={font}:text='{head}':x=10:y=8:fontsize=15:fontcolor=black," \
        "split[a][b];[a]palettegen=max_colors=64[p];[b][p]paletteuse=dither=none"
    out = pictures / "contact-sheets.png"
    run(["ffmpeg", "-hide_banner", "-loglevel", "error", "-y", *inputs, "-filter_complex", graph,
         "-frames:v", "1", out])
    for sheet in tiles:
        sheet.unlink()
    say(f"wrote {out} ({out.stat().st_size // 1024} KB)")
    return out


def median(v):
    return statistics.median(v) if v else float("nan")


def main():
    ap = argparse.ArgumentParser(prog="scripts/bench-library", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", help="package directory (default: the bundled default)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--json", help="results file (default target/bench/library/MODEL.json)")
    ap.add_argument("--pictures", help="draw the contact sheets into this directory")
    ap.add_argument("--fetch-only", action="store_true")
    opt = ap.parse_args()
    if opt.model and not (Path(opt.model) / "choreod-model.toml").is_file():
        fail(f"--model {opt.model}: no choreod-model.toml there (not a model package)")
    if not Path(CHOREOD).is_file():
        fail(f"no choreod binary at {CHOREOD} (cargo build --release -p choreod)")
    if not FIXTURE.is_file():
        fail(f"the AIST++ fixture motion is missing: {FIXTURE}")
    if opt.seeds < 1:
        fail("--seeds must be at least 1")

    sources = fetch_songs()
    excerpts = cut_excerpts(sources)
    print("held-out songs (60 s excerpts; sources' sha256 checked against the pins):")
    for name, character, pkg, path, digest, offset, author in SONGS:
        where = f"Debian {pkg} {DEBIAN[pkg][0]}, {DEBIAN[pkg][1]}" if pkg in DEBIAN else \
            "committed in the repository"
        print(f"  {name:18s} {character}; {where}; {Path(path).name} by {author}; "
              f"sha256 {digest[:16]}...; excerpt {offset:.0f}-{offset + EXCERPT_S:.0f} s")
    if opt.fetch_only:
        return

    load_start = open("/proc/loadavg").read().split()[:3]
    started = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    tag = Path(opt.model).name if opt.model else "default"
    work = ROOT / "target/bench/library" / tag
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()

    fixture = eval_json(FIXTURE)
    fixture_joints = work / "fixture_joints.npy"
    run([CHOREOD, "convert", FIXTURE, "-o", fixture_joints])
    fj = np.load(fixture_joints).astype(np.float64)

    names = [s[0] for s in SONGS]
    tempos, dances, evals, dance_info = {}, {}, {}, {}
    for name in names:
        tempos[name] = tempo(excerpts[name])
        for s in range(opt.seeds):
            out = work / f"{name}_s{s}.h5"
            say(f"dancing {name} seed {s} ({time.monotonic() - t0:.0f} s)")
            dance(excerpts[name], out, s, opt.model)
            dances[(name, s)] = out
            evals[(name, s)] = eval_json(out, excerpts[name])
            dance_info[(name, s)] = read_dance(out)
    first = dance_info[(names[0], 0)]
    label = first["model"]
    fixture_turn = turn_summary(fj, 60.0, first["parents"], first["names"])

    say("pose overlap between songs")
    overlap_t0 = time.monotonic()
    P = {k: poses(v["joints"]) for k, v in dance_info.items()}
    n = len(names)
    matrix = np.full((n, n), np.nan)
    for i, a in enumerate(names):
        for j in range(i + 1, n):
            both = [shares_both_ways(P[(a, s)], P[(names[j], s)]) for s in range(opt.seeds)]
            matrix[i, j] = np.mean([x for x, _ in both])
            matrix[j, i] = np.mean([y for _, y in both])
    same = {}
    for a in names:
        seed_pairs = [shares_both_ways(P[(a, s)], P[(a, t)]) for s in range(opt.seeds)
                      for t in range(s + 1, opt.seeds)]
        same[a] = float(np.mean([x for p in seed_pairs for x in p])) if seed_pairs else float("nan")
    off = matrix[~np.eye(n, dtype=bool)]
    overlap_s = time.monotonic() - overlap_t0
    # Checked on the pair of songs that overlap most, where the most poses are decided.
    ci, cj = np.unravel_index(np.nanargmax(np.nan_to_num(matrix + matrix.T, nan=-1.0)), matrix.shape)
    overlap_check = check_overlap(P[(names[ci], 0)], P[(names[cj], 0)],
                                  f"{names[ci]} / {names[cj]}")

    say("reaction to a tempo/energy change")
    react = reaction(work, opt.seeds, opt.model)

    per_song = []
    for i, name in enumerate(names):
        ev = [evals[(name, s)] for s in range(opt.seeds)]
        turns = [turn_summary(dance_info[(name, s)]["joints"], dance_info[(name, s)]["fps"],
                              dance_info[(name, s)]["parents"], dance_info[(name, s)]["names"])
                 for s in range(opt.seeds)]
        worst = max(turns, key=lambda t: t["max_deg"])
        per_song.append({
            "song": name,
            "character": SONGS[i][1],
            "tempo_bpm": tempos[name],
            "bas_music_beats": float(np.mean([e["bas_music_beats"] for e in ev])),
            "pfc": float(np.mean([e["pfc"] for e in ev])),
            "skate_ratio": float(np.mean([e["skate_ratio"] for e in ev])),
            "max_bone_turn_deg": worst["max_deg"],
            "max_bone_turn_at": f"{worst['bone']}, frame {worst['frame']}",
            "frames_turn_over_60": int(sum(t["frames_over_bar"] for t in turns)),
            "overlap_with_other_songs_median": float(np.nanmedian(matrix[i])),
            "overlap_same_song_other_seed": float(same[name]),
            "per_seed": [{"seed": s, **{k: evals[(name, s)][k] for k in
                                        ("bas_music_beats", "pfc", "skate_ratio")},
                          "bone_turn": turns[s]} for s in range(opt.seeds)],
        })

    bas_mean = float(np.mean([r["bas_music_beats"] for r in per_song]))
    pfc_mean = float(np.mean([r["pfc"] for r in per_song]))
    skate_mean = float(np.mean([r["skate_ratio"] for r in per_song]))
    max_turn = max(per_song, key=lambda r: r["max_bone_turn_deg"])
    firsts = [r["first_moved_window"] for r in react]
    load_end = open("/proc/loadavg").read().split()[:3]

    print(f"\npackage: {label} (sha256 {first['model_sha256'][:16]}...), "
          f"{'--model ' + opt.model if opt.model else 'the bundled default'}; "
          f"seeds 0-{opt.seeds - 1}; {started}; load average {' '.join(load_start)} at start, "
          f"{' '.join(load_end)} at end; {time.monotonic() - t0:.0f} s, of which pose overlap "
          f"{overlap_s:.0f} s ({n * (n - 1) // 2 * opt.seeds} song pairs + "
          f"{n * opt.seeds * (opt.seeds - 1) // 2} seed pairs, both ways)")
    print(f"pose overlap check, seed 0, {overlap_check['pair']}, both ways: pruned = exhaustive "
          f"(frames near {overlap_check['frames_near']}), {overlap_check['pruned_s']:.2f} s vs "
          f"{overlap_check['exhaustive_s']:.2f} s")
    print("\n| song | character | tracked BPM | bas_music_beats | PFC (x fixture) | "
          "skate_ratio (x fixture) | largest bone turn / frame | overlap with other songs "
          "(median) | same song, other seed |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in per_song:
        print(f"| {r['song']} | {r['character']} | {r['tempo_bpm']:.0f} | "
              f"{r['bas_music_beats']:.3f} | {r['pfc']:.3f} ({r['pfc'] / fixture['pfc']:.2f}x) | "
              f"{r['skate_ratio']:.4f} ({r['skate_ratio'] / fixture['skate_ratio']:.2f}x) | "
              f"{r['max_bone_turn_deg']:.1f}° ({r['max_bone_turn_at']}) | "
              f"{r['overlap_with_other_songs_median']:.2f} | "
              f"{r['overlap_same_song_other_seed']:.2f} |")
    print(f"| AIST++ fixture motion | | | | {fixture['pfc']:.3f} | {fixture['skate_ratio']:.4f} | "
          f"{fixture_turn['max_deg']:.1f}° ({fixture_turn['bone']}) | | |")
    print("\npose overlap matrix (row A, column B: share of A's frames within 3 cm of B's dance; "
          "mean over seeds):")
    print("| A \\ B | " + " | ".join(names) + " |")
    print("|---" * (n + 1) + "|")
    for i, a in enumerate(names):
        cells = " | ".join("—" if i == j else f"{matrix[i, j]:.2f}" for j in range(n))
        print(f"| {a} | {cells} |")
    print(f"\nreaction: quiet 90 BPM clicks -> loud 160 BPM at {CHANGE_S:.0f} s, windows of "
          f"{STRIDE_S} s (negative: before the change); per window energy (mean joint speed, "
          "m/s) / kinematic-beat tempo (per min); * = left its dance's own level before the "
          f"change by >= {SEPARATES}x towards the 160-BPM-only dance's level; control = the "
          "90-BPM-only (A -> A) dance's windows after the change (must not move)")
    for r in react:
        lv = ", ".join(f"{c} {r['levels_before']['change'][c]:.2f} -> {r['level_new_music'][c]:.2f}"
                       f" (A-only dance before: {r['levels_before']['steady'][c]:.2f})"
                       for c in CHARACTERS)
        print(f"  seed {r['seed']}: spliced dance before -> 160-BPM-only dance: {lv}; separating: "
              f"{', '.join(r['separating']) or 'none (no change to detect)'}; first moved window "
              f"{r['first_moved_window']}; after-windows moved {r['after_windows_moved']}/"
              f"{REACTION_AFTER}; control windows moved {r['control_windows_moved']}/"
              f"{REACTION_AFTER}; windows before the change moved {r['before_windows_moved']}/"
              f"{REACTION_BEFORE}")
        for key in ("change", "steady"):
            cells = ", ".join(f"{w['window']:+d}: {w['energy']:.2f}/{w['tempo']:.0f}"
                              f"{'*' if w['moved'] else ''}" for w in r["windows"][key])
            print(f"    {key:6s} {cells}")
    print(f"\nsummary ({label}):")
    print(f"  pose overlap between songs, median of the {n}x{n - 1} matrix: "
          f"{float(np.median(off)):.2f} (target <= 0.5); same song, other seed: "
          f"{float(np.nanmean(list(same.values()))):.2f}")
    print(f"  bas_music_beats, mean over songs and seeds: {bas_mean:.3f} (target >= 0.39)")
    print(f"  PFC mean {pfc_mean:.3f} = {pfc_mean / fixture['pfc']:.2f}x the fixture's; "
          f"skate_ratio mean {skate_mean:.4f} = {skate_mean / fixture['skate_ratio']:.2f}x "
          "(target <= 1x)")
    print(f"  largest bone turn / frame at 30 fps: {max_turn['max_bone_turn_deg']:.1f}° "
          f"({max_turn['song']}, {max_turn['max_bone_turn_at']}; target <= 60°); AIST++ fixture "
          f"{fixture_turn['max_deg']:.1f}°")
    print(f"  reaction, first moved window after the change per seed: {firsts} (target <= 2); "
          f"control windows moved: {[r['control_windows_moved'] for r in react]} (must be 0)")

    result = {
        "command": "scripts/bench-library" + (f" --model {opt.model}" if opt.model else ""),
        "package": label, "package_sha256": first["model_sha256"], "seeds": opt.seeds,
        "started_utc": started, "load_average_start": load_start, "load_average_end": load_end,
        "songs": per_song, "overlap_seconds": overlap_s,
        "overlap_check": overlap_check,
        "overlap": {"songs": names, "matrix": matrix.tolist(), "median": float(np.median(off)),
                    "same_song_other_seed_mean": float(np.nanmean(list(same.values())))},
        "bas_music_beats_mean": bas_mean,
        "fixture": {"pfc": fixture["pfc"], "skate_ratio": fixture["skate_ratio"],
                    "max_bone_turn": fixture_turn},
        "pfc_mean": pfc_mean, "skate_ratio_mean": skate_mean,
        "max_bone_turn_deg": max_turn["max_bone_turn_deg"],
        "reaction": {"change_s": CHANGE_S, "stride_s": STRIDE_S, "separates": SEPARATES,
                     "kinematic_sigma_s": KINEMATIC_SIGMA_S, "per_seed": react},
    }
    out = Path(opt.json) if opt.json else ROOT / "target/bench/library" / f"{label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"\nwrote {out}")
    if opt.pictures:
        contact_sheets(dances, Path(opt.pictures), label, tempos)


if __name__ == "__main__":
    main()
