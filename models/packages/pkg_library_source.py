"""The dance library (library-source/): real dance on one SMPL-24 body, 30 fps.

Every clip of ../shared/data/dance-mocap (CMU dance in four styles, four rigs) and the AIST++
fixture clip, each as float32 (T, 24, 3) SMPL joint positions: metres, y-up, 30 fps, SMPL joint
order (Stanford-TML/EDGE vis.py `smpl_joints`), floor at y = 0, root xz = 0 and facing +z at
frame 0, every bone at the SMPL neutral rest length of EDGE vis.py `smpl_offsets` (the body of
exemplar-source/) with its direction from the source.

Steps per CMU clip (`build(...)`):
1. gunzip the .bvh.gz into a temporary directory;
2. `choreod convert CLIP.bvh --to smpl24 -o CLIP.h5`: choreod's one BVH reader and one rig
   table place the rig on SMPL-24 by joint names (datasets/src/kinematics/rig.rs);
3. z-up sources turned y-up (a rotation about x), measured, not assumed: the axis of the mean
   pelvis-to-head vector;
4. resampled to 30 fps at the verified frame time (linear interpolation at k / 30 s, which is an
   exact decimation for the 60 and 120 fps sources, as EDGE data/slice.py takes every other frame);
5. retargeted onto one body (`retarget`): root trajectory scaled by SMPL's leg length over the
   source's, every bone re-laid from its parent at SMPL's rest length along the source bone;
6. glitches cut (`split_at_glitches`): a bone that turns more than GLITCH_TURN_DEG between two
   30 fps frames is a marker swap or a T-pose frame, not dance;
7. grounded and faced (`ground_and_face`).
"""

from __future__ import annotations

import gzip
import json
import pickle
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

import pkg_common as C

FPS = 30.0
# Ankles and toes (EDGE vis.py smpl_joints: lankle 7, rankle 8, ltoes 10, rtoes 11): the floor
# is the lowest of them over the clip, as exemplar-source/ grounds the AIST++ loop.
FOOT_JOINTS = (7, 8, 10, 11)
HEAD, PELVIS, LHIP, RHIP, LKNEE, RKNEE, LANKLE, RANKLE = 15, 0, 1, 2, 4, 5, 7, 8
BONES = [(p, j) for j, p in enumerate(C.SMPL_PARENTS) if p >= 0]
REST_LENGTHS = np.linalg.norm(C.SMPL_OFFSETS, axis=1)  # SMPL neutral rest bone lengths (metres)
# A bone turning more than this between two frames at 30 fps is a capture glitch: the AIST++
# fixture's largest turn is 20 degrees per frame (issue 24), and a marker swap or the T-pose that
# cgspeed-style conversions put in frame 0 turns limbs by 90-180 degrees at once.
GLITCH_TURN_DEG = 90.0
# Frames dropped on each side of a glitch (0.5 s): the capture settles over a few frames.
GLITCH_MARGIN = 15
# Pieces shorter than this after cutting are dropped (2 s: shorter than the 2.5 s stride of the
# model's windows); a clip without glitches is kept whatever its length.
MIN_PIECE_FRAMES = 60

AISTPP_PKL = "fixtures/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"

# Salsa basic: steps on 1, 2, 3 and 5, 6, 7 of each eight beats (salsanorthwest.com "Dancing the
# Basic Step": "Only six of the eight beats are used"), so the feet change weight 0.75 times per
# music beat and come together every 4 beats.
SALSA_STEPS_PER_BEAT = 0.75
SALSA_BPM = (180.0, 210.0)  # dance-mocap/README.md: the music's usual tempo range

MIRROR_HONEST = {
    "salsa-lead": (False, "a mirrored lead steps forward on the right foot on 1 and holds the partner with "
                   "the wrong hands: neither the lead's nor the follow's part (the follow steps back on the "
                   "right on 1), and both real roles are in the library already"),
    "salsa-follow": (False, "a mirrored follow steps back on the left on 1 with the wrong hand raised in the "
                     "hold: not the lead (who steps forward on the left), and not a follow"),
    "modern": (True, "ballet and modern vocabulary (pirouettes, arabesques, jetes) is danced to both sides"),
    "breakdance": (True, "toprock, footwork and power moves are danced in either direction"),
    "free": (True, "free dance has no handed convention"),
    "aistpp-break": (True, "break dance is danced to either side; AIST++-trained models mirror it"),
}

# Source folders (dance-mocap/README.md): style per CMU subject, the frame time in the files and
# the one used (salsa: measured by `salsa_rate_evidence`; README.md of the library gives the
# numbers), the rig choreod's table should find (checked), and whether frame 0 is a T-pose the
# conversion may have added (cgspeed-style conversions do: cgspeed READMEFIRST, "Every BVH file
# has a T-pose added as its new first frame"); it is dropped where it is one (`is_t_pose`).
SOURCES = [
    {"folder": "cmu-60-61-salsa", "subject": "60", "style": "salsa-lead", "rig": "Poser",
     "file_frame_time": 1 / 120, "frame_time": 1 / 60, "t_pose_first": True},
    {"folder": "cmu-60-61-salsa", "subject": "61", "style": "salsa-follow", "rig": "Poser",
     "file_frame_time": 1 / 120, "frame_time": 1 / 60, "t_pose_first": True},
    {"folder": "cmu-05-modern", "subject": "05", "style": "modern", "rig": "Reallusion CC_Base",
     "file_frame_time": 1 / 60, "frame_time": 1 / 60},
    {"folder": "cmu-85-breakdance", "subject": "85", "style": "breakdance", "rig": "Neo",
     "file_frame_time": 1 / 30, "frame_time": 1 / 30},
    {"folder": "cmu-55-dance", "subject": "55", "style": "free", "rig": "CMU MotionBuilder",
     "file_frame_time": 1 / 120, "frame_time": 1 / 120},
]
BREAKDANCE_TITLES = {"85_03": "UpRightSequence", "85_04": "FancyFootWork", "85_12": "LongSequenceGood",
                     "85_14": "BreakSequencewithFlips"}


def source_clips(mocap: Path) -> list[dict]:
    """One entry per source file: its path, CMU trial and folder settings."""
    out = []
    for src in SOURCES:
        for path in sorted((mocap / src["folder"]).glob("*.bvh.gz")):
            stem = path.name.removesuffix(".bvh.gz").removesuffix("_scaled")
            subject, trial = stem.split("_")[:2]
            subject = subject.lstrip("0").rjust(2, "0")
            if subject != src["subject"]:
                continue
            out.append(dict(src, path=path, trial=f"{subject}_{trial}"))
    return out


# --- Geometry --------------------------------------------------------------------------------

def resample(joints: np.ndarray, fps_in: float, fps_out: float = FPS) -> np.ndarray:
    """Positions at k / fps_out s (k = 0.. while inside the clip), linear between source frames.

    For an integer ratio (60 or 120 fps to 30) every output frame is a source frame exactly.
    """
    n = joints.shape[0]
    count = int(np.floor((n - 1) * fps_out / fps_in + 1e-9)) + 1
    u = np.arange(count) * (fps_in / fps_out)
    lo = np.minimum(np.floor(u + 1e-9).astype(int), n - 1)
    hi = np.minimum(lo + 1, n - 1)
    frac = np.clip(u - lo, 0.0, 1.0)[:, None, None]
    return joints[lo] * (1.0 - frac) + joints[hi] * frac


def to_y_up(joints: np.ndarray) -> tuple[np.ndarray, str]:
    """The clip turned so that its mean pelvis-to-head direction is +y, by a quarter or half turn
    about x or z (a proper rotation: handedness kept), and the source axis that was up."""
    up = (joints[:, HEAD] - joints[:, PELVIS]).mean(axis=0)
    axis = int(np.argmax(np.abs(up)))
    sign = 1.0 if up[axis] > 0 else -1.0
    name = ("+" if sign > 0 else "-") + "xyz"[axis]
    x, y, z = joints[..., 0], joints[..., 1], joints[..., 2]
    turned = {
        "+y": (x, y, z), "-y": (x, -y, -z),           # half turn about x
        "+z": (x, z, -y), "-z": (x, -z, y),           # quarter turns about x
        "+x": (-y, x, z), "-x": (y, -x, z),           # quarter turns about z
    }[name]
    return np.stack(turned, axis=-1), name


def is_t_pose(frame: np.ndarray) -> bool:
    """Both upper arms (SMPL shoulder to elbow, 16-18 and 17-19) within 40 degrees of level (the
    salsa files' added first frames hold them 22-30 degrees below level; dancing, 75-85)."""
    for shoulder, elbow in ((16, 18), (17, 19)):
        d = frame[elbow] - frame[shoulder]
        if abs(d[1]) > np.sin(np.radians(40.0)) * np.linalg.norm(d):
            return False
    return True


def leg_length(joints: np.ndarray) -> float:
    """Median over frames of hip-knee-ankle length, mean of both legs (metres)."""
    legs = []
    for hip, knee, ankle in ((LHIP, LKNEE, LANKLE), (RHIP, RKNEE, RANKLE)):
        legs.append(np.linalg.norm(joints[:, knee] - joints[:, hip], axis=-1)
                    + np.linalg.norm(joints[:, ankle] - joints[:, knee], axis=-1))
    return float(np.median(np.mean(legs, axis=0)))


SMPL_LEG = float(REST_LENGTHS[LKNEE] + REST_LENGTHS[LANKLE] + REST_LENGTHS[RKNEE] + REST_LENGTHS[RANKLE]) / 2.0


def retarget(joints: np.ndarray) -> np.ndarray:
    """The clip on SMPL's body: each bone at its SMPL rest length along the source bone.

    The root trajectory is scaled by SMPL's leg length over the source's (a longer-legged dancer
    travels further per step, so the feet keep still where the source's did); then, in SMPL's
    tree order (parents first), joint j = joint parent(j) + rest length(j) x unit(source bone j).
    A zero-length source bone (never in the library's sources) takes its SMPL rest direction.
    """
    src = np.asarray(joints, dtype=np.float64)
    out = np.zeros_like(src)
    out[:, PELVIS] = src[:, PELVIS] * (SMPL_LEG / leg_length(src))
    for parent, j in BONES:
        d = src[:, j] - src[:, parent]
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        unit = np.where(n > 1e-9, d / np.maximum(n, 1e-12), C.SMPL_OFFSETS[j] / REST_LENGTHS[j])
        out[:, j] = out[:, parent] + REST_LENGTHS[j] * unit
    return out


def ground_and_face(joints: np.ndarray) -> tuple[np.ndarray, dict]:
    """Floor at y = 0 (the clip's lowest ankle/toe), root xz = 0 and the hips across +x at frame 0.

    A turn about y by the angle of frame 0's left-minus-right hip vector in the xz plane puts the
    left hip toward +x; with y up that faces +z (SMPL's rest pose). Rigid: bone lengths kept.
    """
    j = np.asarray(joints, dtype=np.float64)
    across = j[0, LHIP] - j[0, RHIP]
    phi = np.arctan2(across[2], across[0])
    c, s = np.cos(phi), np.sin(phi)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    out = j @ rot.T
    floor = out[:, FOOT_JOINTS, 1].min()
    out[..., 1] -= floor
    out[..., [0, 2]] -= out[0, PELVIS, [0, 2]]
    return out, {"turn_about_y_deg": float(np.degrees(phi)), "floor_shift_m": float(-floor)}


def bone_turns_deg(joints: np.ndarray) -> np.ndarray:
    """(T-1, 23): the angle each bone turns between consecutive frames, degrees."""
    j = np.asarray(joints, dtype=np.float64)
    par = [p for p, _ in BONES]
    child = [c for _, c in BONES]
    d = j[:, child] - j[:, par]
    d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    cos = np.clip((d[1:] * d[:-1]).sum(axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def split_at_glitches(joints: np.ndarray) -> tuple[list[tuple[int, int]], list[int]]:
    """Pieces [a, b) of the clip between glitch frames, each at least MIN_PIECE_FRAMES long.

    A glitch is a frame pair (t, t+1) where some bone turns more than GLITCH_TURN_DEG; frames
    within GLITCH_MARGIN of it are dropped. Returns the pieces and the glitch frames t.
    """
    turns = bone_turns_deg(joints).max(axis=1)
    glitches = [int(t) for t in np.flatnonzero(turns > GLITCH_TURN_DEG)]
    if not glitches:
        return [(0, joints.shape[0])], []
    bad = np.zeros(joints.shape[0], dtype=bool)
    for t in glitches:
        bad[max(0, t - GLITCH_MARGIN + 1):t + GLITCH_MARGIN + 1] = True
    pieces, start = [], None
    for f in range(joints.shape[0] + 1):
        good = f < joints.shape[0] and not bad[f]
        if good and start is None:
            start = f
        elif not good and start is not None:
            if f - start >= MIN_PIECE_FRAMES:
                pieces.append((start, f))
            start = None
    return pieces, glitches


def facing_check(joints: np.ndarray) -> float:
    """Mean over frames of the toes' direction from the ankles along the body's facing
    (left-minus-right hip x up): positive for a right-handed, un-mirrored body."""
    across = joints[:, LHIP] - joints[:, RHIP]
    facing = np.cross(across, np.array([0.0, 1.0, 0.0]))
    facing /= np.maximum(np.linalg.norm(facing, axis=-1, keepdims=True), 1e-12)
    feet = 0.5 * ((joints[:, 10] - joints[:, LANKLE]) + (joints[:, 11] - joints[:, RANKLE]))
    return float((feet * facing).sum(axis=-1).mean())


def clip_checks(joints: np.ndarray) -> dict:
    """The numbers README.md reports per clip (metres, m/s, degrees)."""
    j = np.asarray(joints, dtype=np.float64)
    lengths = np.linalg.norm(j[:, [c for _, c in BONES]] - j[:, [p for p, _ in BONES]], axis=-1)
    speed = np.linalg.norm(np.diff(j, axis=0), axis=-1) * FPS
    lowest_foot = j[:, FOOT_JOINTS, 1].min(axis=1)
    turns = bone_turns_deg(j)
    return {
        "head_above_pelvis_mean_m": round(float((j[:, HEAD, 1] - j[:, PELVIS, 1]).mean()), 3),
        "lowest_foot_m": {"min": round(float(lowest_foot.min()), 4),
                          "median": round(float(np.median(lowest_foot)), 4),
                          "p95": round(float(np.percentile(lowest_foot, 95)), 4)},
        "lowest_joint_m": round(float(j[..., 1].min()), 4),
        "joint_speed_p99_m_s": round(float(np.percentile(speed, 99)), 3),
        "max_bone_turn_deg_per_frame": round(float(turns.max()), 2),
        "bone_turn_p99_deg_per_frame": round(float(np.percentile(turns, 99)), 2),
        "bone_length_max_error_m": float(np.abs(lengths - REST_LENGTHS[1:]).max()),
        "toes_forward_m": round(facing_check(j), 4),
    }


# --- Sources ---------------------------------------------------------------------------------

def choreod_smpl24(choreod: Path, bvh: Path, tmp: Path) -> tuple[np.ndarray, float, str]:
    """SMPL-24 joints of a BVH placed by choreod's rig table, its frame rate and what choreod
    said it did (the rig's name)."""
    import h5py

    out = tmp / (bvh.stem + ".h5")
    res = subprocess.run([str(choreod), "convert", str(bvh), "--to", "smpl24", "-o", str(out)],
                         capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise SystemExit(f"choreod convert {bvh.name} --to smpl24 failed: {res.stderr.strip()}")
    with h5py.File(out, "r") as f:
        joints = f["motion/joints"][()].astype(np.float64)
        fps = float(f["motion"].attrs["fps"])
    out.unlink()
    return joints, fps, res.stdout.strip()


def aistpp_joints(pkl_path: Path) -> np.ndarray:
    """The whole AIST++ fixture on SMPL's body at 30 fps, derived as exemplar-source/ is: SMPL FK
    with EDGE vis.py's rest offsets of the pickle's poses, root = smpl_trans / smpl_scaling
    (google/aistplusplus_api demos/extract_motion_feats.py), every other frame (60 -> 30 fps,
    EDGE data/slice.py)."""
    with open(pkl_path, "rb") as f:
        d = pickle.load(f)  # trusted fixture (build script only)
    poses = np.asarray(d["smpl_poses"], dtype=np.float64)
    poses = poses.reshape(poses.shape[0], C.N_JOINTS, 3)[::2]
    scaling = float(np.asarray(d["smpl_scaling"], dtype=np.float64).ravel()[0])
    root = (np.asarray(d["smpl_trans"], dtype=np.float64).reshape(-1, 3) / scaling)[::2]
    return C.smpl_forward_kinematics(poses, root)


def kinematic_beat_rate(joints: np.ndarray) -> float:
    """Bailando's kinematic beats (local minima of the smoothed mean joint speed, as
    pkg_exemplar.kinematic_beats_60 finds them) per second of a 30 fps clip."""
    import pkg_exemplar

    beats = pkg_exemplar.kinematic_beats_60(joints)
    return beats.size / (joints.shape[0] / FPS)


def basic_cycle_period_s(joints: np.ndarray) -> float:
    """Period (s) of the left ankle's fore-aft position relative to the pelvis, along the body's
    facing (1 s Gaussian high-pass against the drift of the stance): its autocorrelation's
    highest value between 0.5 and 5 s. In a salsa basic the left foot goes forward on 1 and back
    on 5 (lead; the follow mirrors it), so one cycle is 8 beats."""
    from scipy.ndimage import gaussian_filter1d

    across = joints[:, LHIP] - joints[:, RHIP]
    facing = np.cross(across, np.array([0.0, 1.0, 0.0]))
    facing /= np.maximum(np.linalg.norm(facing, axis=-1, keepdims=True), 1e-12)
    x = ((joints[:, LANKLE] - joints[:, PELVIS]) * facing).sum(axis=-1)
    x = x - gaussian_filter1d(x, FPS)
    ac = np.correlate(x, x, "full")[x.size - 1:]
    lo, hi = int(0.5 * FPS), min(int(5.0 * FPS), x.size - 1)
    return (lo + int(np.argmax(ac[lo:hi]))) / FPS


def salsa_rate_evidence(upright: np.ndarray) -> dict:
    """What a salsa clip's motion says under each frame-time assumption (120 fps as the files
    say, 60 fps as CMU's listing says): kinematic beats per second, the period of the basic's fore-aft foot cycle and the music tempo it implies (8 beats per
    cycle), and the 99th percentile ankle speed."""
    out = {}
    for fps in (120.0, 60.0):
        body = retarget(resample(upright, fps))
        pieces, _ = split_at_glitches(body)
        a, b = max(pieces, key=lambda p: p[1] - p[0], default=(0, body.shape[0]))
        j = body[a:b]
        period = basic_cycle_period_s(j)
        ankle = np.linalg.norm(np.diff(j[:, [LANKLE, RANKLE]], axis=0), axis=-1) * FPS
        out[f"{fps:.0f}fps"] = {
            "kinematic_beats_per_s": round(kinematic_beat_rate(j), 3),
            "basic_cycle_period_s": round(period, 3),
            "implied_bpm": round(8.0 * 60.0 / period, 1),
            "ankle_speed_p99_m_s": round(float(np.percentile(ankle, 99)), 3),
        }
    return out


# --- Build -----------------------------------------------------------------------------------

def derive_clip(upright: np.ndarray, up_axis: str, fps: float) -> tuple[list[tuple[np.ndarray, dict]], dict]:
    """Source SMPL-24 positions (y-up) at `fps` -> library pieces (float64) with their info."""
    j30 = resample(upright, fps)
    body = retarget(j30)
    pieces, glitches = split_at_glitches(body)
    out = []
    for a, b in pieces:
        placed, info = ground_and_face(body[a:b])
        out.append((placed, dict(info, source_frames_30fps=[a, b])))
    info = {"source_up_axis": up_axis, "frames_30fps_before_cuts": int(j30.shape[0]),
            "glitch_frames_30fps": glitches,
            "source_leg_length_m": round(leg_length(upright), 4)}
    return out, info


def build(out_dir: Path, shared: Path, choreod: Path) -> list[dict]:
    """Write the library into out_dir (.npy per clip + clips.json); returns the clip records."""
    mocap = shared / "data" / "dance-mocap"
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("*.npy"):
        old.unlink()
    records, evidence = [], {}
    with tempfile.TemporaryDirectory(prefix="library-source-") as tmp_name:
        tmp = Path(tmp_name)
        for src in source_clips(mocap):
            bvh = tmp / src["path"].name.removesuffix(".gz")
            with gzip.open(src["path"], "rb") as fin, open(bvh, "wb") as fout:
                shutil.copyfileobj(fin, fout)
            joints, fps_file, said = choreod_smpl24(choreod, bvh, tmp)
            bvh.unlink()
            if src["rig"] not in said:
                raise SystemExit(f"{src['path'].name}: expected the {src['rig']} rig, choreod said: {said}")
            if abs(1.0 / fps_file - src["file_frame_time"]) > 1e-6:
                raise SystemExit(f"{src['path'].name}: frame time {1 / fps_file} in the file, expected "
                                 f"{src['file_frame_time']}")
            upright, up_axis = to_y_up(joints)
            t_pose = bool(src.get("t_pose_first")) and is_t_pose(upright[0])
            if t_pose:
                upright = upright[1:]
            pieces, info = derive_clip(upright, up_axis, 1.0 / src["frame_time"])
            if src["style"].startswith("salsa"):
                evidence[src["trial"]] = salsa_rate_evidence(upright)
            for k, (placed, piece_info) in enumerate(pieces):
                suffix = "" if len(pieces) == 1 else "abcdefgh"[k]
                name = f"cmu_{src['trial']}{suffix}"
                records.append(save_clip(out_dir, name, placed, {
                    "style": src["style"],
                    "source": str(src["path"].relative_to(shared)),
                    "cmu_trial": src["trial"],
                    **({"title": BREAKDANCE_TITLES[src["trial"]]} if src["trial"] in BREAKDANCE_TITLES else {}),
                    "source_rig": src["rig"],
                    "source_frame_time_in_file_s": round(src["file_frame_time"], 6),
                    "source_frame_time_used_s": round(src["frame_time"], 6),
                    "t_pose_frame_dropped": t_pose,
                    **info, **piece_info,
                }))
        placed, info = ground_and_face(aistpp_joints(shared / AISTPP_PKL))
        records.append(save_clip(out_dir, "aistpp_gBR_sBM_cAll_d04_mBR0_ch01", placed, {
            "style": "aistpp-break",
            "source": AISTPP_PKL,
            "cmu_trial": None,
            "source_rig": "SMPL (AIST++ poses, EDGE vis.py rest offsets)",
            "source_frame_time_in_file_s": round(1 / 60, 6),
            "source_frame_time_used_s": round(1 / 60, 6),
            **info,
        }))
    (out_dir / "clips.json").write_text(json.dumps({
        "format": "choreod-dance-library", "format_version": 1, "fps": FPS, "skeleton": "smpl24",
        "clips": records, "salsa_frame_rate_evidence": summarise_evidence(evidence)}, indent=1) + "\n")
    return records


def summarise_evidence(evidence: dict) -> dict:
    """Per salsa clip and the medians over them, under each frame-time assumption."""
    medians = {}
    for rate in ("120fps", "60fps"):
        keys = next(iter(evidence.values()))[rate].keys()
        medians[rate] = {k: round(float(np.median([e[rate][k] for e in evidence.values()])), 3) for k in keys}
    lo, hi = SALSA_BPM
    return {
        "expected": {"music_bpm": [lo, hi],
                     "weight_changes_per_s": [round(lo * SALSA_STEPS_PER_BEAT / 60, 3),
                                              round(hi * SALSA_STEPS_PER_BEAT / 60, 3)],
                     "basic_cycle_period_s": [round(8 * 60 / hi, 3), round(8 * 60 / lo, 3)]},
        "clips_with_implied_bpm_150_to_250": {
            rate: sum(150.0 <= e[rate]["implied_bpm"] <= 250.0 for e in evidence.values()) for rate in medians},
        "clip_count": len(evidence),
        "median": medians, "clips": evidence}


def save_clip(out_dir: Path, name: str, joints: np.ndarray, meta: dict) -> dict:
    data = joints.astype(np.float32)
    np.save(out_dir / f"{name}.npy", data, allow_pickle=False)
    honest, why = MIRROR_HONEST[meta["style"]]
    checks = clip_checks(data)
    return {"name": name, "file": f"{name}.npy", **meta,
            "frames": int(data.shape[0]), "seconds": round(data.shape[0] / FPS, 3),
            "mirror_honest": honest, "mirror_why": why,
            "max_bone_turn_deg_per_frame": checks["max_bone_turn_deg_per_frame"],
            "checks": checks}
