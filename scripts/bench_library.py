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
- reaction to a change (the offline peer of `scripts/bench-live --click`): a synthetic song of a
  quiet 90 BPM click track that turns, at a known time, into a loud 160 BPM one, danced next to
  the 90 BPM track alone (same seed). In 2.5 s windows (the sampler's stride) after the change:
  the share of the window's frames within 3 cm of any pose of the 90-BPM-only dance, and the
  window's mean joint speed over the 90-BPM-only dance's in the same window. A window has
  changed when that share falls below 0.5 or the speed ratio leaves [0.8, 1.25]; the reaction
  is the first changed window (1 = the 2.5 s right after the change). The windows before the
  change are the control (they should not have changed).
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
CHANGED_SHARE = 0.5
SPEED_BAND = (0.8, 1.25)

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
    on the eighths. `change`: A until CHANGE_S, then B, 61 s in all; `steady`: A throughout."""
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
    paths = {"change": work / "click_90quiet_then_160loud.wav", "steady": work / "click_90quiet.wav"}
    write_wav(paths["change"], change, sr)
    write_wav(paths["steady"], steady, sr)
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
    """For every pose of a (Ta, J, 3), the smallest mean joint distance to any pose of b."""
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


def share_near(a, b):
    return float((nearest_mean_joint_distance(a, b) <= NEAR_M).mean())


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


def mean_speed(joints, fps):
    """Mean joint speed (m/s) over the frames given."""
    return float(np.linalg.norm(np.diff(joints, axis=0), axis=-1).mean() * fps)


def reaction(work, seeds, model):
    clicks = click_songs(work)
    per_seed = []
    for s in range(seeds):
        d = {}
        for key, path in clicks.items():
            out = work / f"click_{key}_s{s}.h5"
            say(f"  reaction: dancing {path.name} seed {s}")
            dance(path, out, s, model)
            d[key] = read_dance(out)
        fps = d["change"]["fps"]
        steady_poses = poses(d["steady"]["joints"])
        windows = []
        for k in list(range(-3, 0)) + list(range(1, 10)):
            lo = CHANGE_S + (k - 1) * STRIDE_S if k > 0 else CHANGE_S + k * STRIDE_S
            f0, f1 = int(round(lo * fps)), int(round((lo + STRIDE_S) * fps))
            jc, js = d["change"]["joints"][f0:f1], d["steady"]["joints"][f0:f1]
            if len(jc) < 2 or len(js) < 2:
                continue
            share = share_near(poses(jc), steady_poses)
            ratio = mean_speed(jc, fps) / max(mean_speed(js, fps), 1e-9)
            changed = share < CHANGED_SHARE or not SPEED_BAND[0] <= ratio <= SPEED_BAND[1]
            windows.append({"window": k, "start_s": lo, "share_near_steady": share,
                            "speed_ratio": ratio, "changed": bool(changed)})
        after = [w for w in windows if w["window"] > 0]
        first = next((w["window"] for w in after if w["changed"]), None)
        per_seed.append({"seed": s, "first_changed_window": first,
                         "control_windows_changed": sum(w["changed"] for w in windows
                                                        if w["window"] < 0),
                         "windows": windows})
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
    P = {k: poses(v["joints"]) for k, v in dance_info.items()}
    n = len(names)
    matrix = np.full((n, n), np.nan)
    for i, a in enumerate(names):
        for j, b in enumerate(names):
            if i != j:
                matrix[i, j] = np.mean([share_near(P[(a, s)], P[(b, s)]) for s in range(opt.seeds)])
    same = {a: (np.mean([share_near(P[(a, s)], P[(a, t)]) for s in range(opt.seeds)
                         for t in range(opt.seeds) if s != t]) if opt.seeds > 1 else float("nan"))
            for a in names}
    off = matrix[~np.eye(n, dtype=bool)]

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
    firsts = [r["first_changed_window"] for r in react]
    load_end = open("/proc/loadavg").read().split()[:3]

    print(f"\npackage: {label} (sha256 {first['model_sha256'][:16]}...), "
          f"{'--model ' + opt.model if opt.model else 'the bundled default'}; "
          f"seeds 0-{opt.seeds - 1}; {started}; load average {' '.join(load_start)} at start, "
          f"{' '.join(load_end)} at end; {time.monotonic() - t0:.0f} s")
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
    print("\nreaction: quiet 90 BPM clicks -> loud 160 BPM at "
          f"{CHANGE_S:.0f} s; per window of {STRIDE_S} s (negative: before the change, control): "
          "share within 3 cm of the 90-BPM-only dance / speed ratio to it")
    for r in react:
        cells = ", ".join(f"{w['window']:+d}: {w['share_near_steady']:.2f}/"
                          f"{w['speed_ratio']:.2f}{'*' if w['changed'] else ''}"
                          for w in r["windows"])
        print(f"  seed {r['seed']}: first changed window {r['first_changed_window']}; "
              f"control windows changed {r['control_windows_changed']}; {cells}")
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
    print(f"  reaction, first changed window after the change per seed: {firsts} (target <= 2)")

    result = {
        "command": "scripts/bench-library" + (f" --model {opt.model}" if opt.model else ""),
        "package": label, "package_sha256": first["model_sha256"], "seeds": opt.seeds,
        "started_utc": started, "load_average_start": load_start, "load_average_end": load_end,
        "songs": per_song,
        "overlap": {"songs": names, "matrix": matrix.tolist(), "median": float(np.median(off)),
                    "same_song_other_seed_mean": float(np.nanmean(list(same.values())))},
        "bas_music_beats_mean": bas_mean,
        "fixture": {"pfc": fixture["pfc"], "skate_ratio": fixture["skate_ratio"],
                    "max_bone_turn": fixture_turn},
        "pfc_mean": pfc_mean, "skate_ratio_mean": skate_mean,
        "max_bone_turn_deg": max_turn["max_bone_turn_deg"],
        "reaction": {"change_s": CHANGE_S, "stride_s": STRIDE_S, "changed_share": CHANGED_SHARE,
                     "speed_band": SPEED_BAND, "per_seed": react},
    }
    out = Path(opt.json) if opt.json else ROOT / "target/bench/library" / f"{label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"\nwrote {out}")
    if opt.pictures:
        contact_sheets(dances, Path(opt.pictures), label, tempos)


if __name__ == "__main__":
    main()
