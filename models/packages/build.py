#!/usr/bin/env python3
"""Build and check choreod's shipped model packages (reproducible byte for byte).

    python models/packages/build.py source                      # re-derive exemplar-source/*.npy
    python models/packages/build.py library-source              # re-derive library-source/ (choreod built)
    python models/packages/build.py exemplar --out models/packages/exemplar [--exemplars K] [--check]
    python models/packages/build.py library --out models/packages/library [--source DIR] [--check]
    python models/packages/build.py mofusion-ref --size tiny --out models/packages/mofusion-ref [--check]
    python models/packages/build.py mofusion-ref --size paper --out target/bench/mofusion-paper
    python models/packages/build.py style-gaussian --out models/packages/style-gaussian [--rho 0] [--check]
    python models/packages/build.py mcm-ldm-ref --size tiny --out models/packages/mcm-ldm-ref [--check]
    python models/packages/build.py check DIR                   # validate a built package

Run with the project venv (`.venv/bin/python`: onnx 1.23.2, onnxscript 0.7.2, onnxruntime 1.31.1,
numpy 2.x). No torch. See models/packages/README.md for the contract and for exporting your own
trained checkpoint.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import sys
import tomllib
from pathlib import Path

# OpenBLAS picks its kernels by CPU at load time, and its AVX-512 (SkylakeX) kernels round float64
# matrix products differently from its AVX2 (Haswell) ones: on an AVX-512 machine the library
# package came out with another sha256 than its pin (numpy's own SIMD paths made no difference;
# measured 2026-11-27). The pins were made with the Haswell kernels, which every x86-64-v3 CPU
# runs, so those are chosen before numpy loads OpenBLAS (an explicit OPENBLAS_CORETYPE wins).
if platform.machine() == "x86_64":
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import pkg_common as C  # noqa: E402
import pkg_exemplar  # noqa: E402

SOURCE_DIR = HERE / "exemplar-source"
LIBRARY_SOURCE = HERE / "library-source"
SHARED = HERE.parent.parent.parent / "shared"
DEFAULT_PKL = SHARED / "fixtures" / "motion" / "aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"


def load_manifest(pkg: Path) -> dict:
    path = pkg / "choreod-model.toml"
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise SystemExit(f"{path}: {e}") from None


def session(pkg: Path, manifest: dict):
    import onnxruntime as ort

    comp = manifest["components"]["denoiser"]
    path = pkg / comp["file"]
    data = path.read_bytes()
    got = hashlib.sha256(data).hexdigest()
    if got != comp["sha256"]:
        raise SystemExit(f"{path}: sha256 {got} does not match the manifest's {comp['sha256']}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    return ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])


def random_inputs(rng: np.random.Generator, n: int) -> dict:
    return {
        "x_t": rng.standard_normal((n, C.WINDOW_FRAMES, C.DIM)).astype(np.float32),
        "t": rng.integers(0, C.TRAIN_STEPS, size=n).astype(np.int64),
        # log-mel dB values in the range `choreod mel` produces (top_db 80 below a peak near +30)
        "music": rng.uniform(-50.0, 30.0, size=(n, C.MUSIC_FRAMES, C.N_MELS)).astype(np.float32),
        "cond": rng.integers(0, 2, size=n).astype(np.float32),
    }


def fail(msg: str) -> None:
    raise SystemExit(f"check failed: {msg}")


def check_contract(pkg: Path, m: dict, sess, music_matters: bool) -> None:
    """Checks every package must pass: manifest, sha256, tensor names/dtypes, N=1 and N=4 runs."""
    if m.get("format") != "choreod-model" or m.get("format_version") != 1:
        fail(f"{pkg}: format/format_version")
    comp = m["components"]["denoiser"]
    dt = {"float32": "tensor(float)", "int64": "tensor(int64)"}
    got_in = [(i.name, i.type) for i in sess.get_inputs()]
    want_in = [(i["name"], dt[i["dtype"]]) for i in comp["inputs"]]
    if got_in != want_in:
        fail(f"inputs {got_in} != manifest {want_in}")
    got_out = [(o.name, o.type) for o in sess.get_outputs()]
    want_out = [(o["name"], dt[o["dtype"]]) for o in comp["outputs"]]
    if got_out != want_out:
        fail(f"outputs {got_out} != manifest {want_out}")
    rng = np.random.default_rng(1234)
    feeds4 = random_inputs(rng, 4)
    (pred4,) = sess.run(["pred"], feeds4)
    if pred4.shape != (4, C.WINDOW_FRAMES, C.DIM) or pred4.dtype != np.float32:
        fail(f"N=4 output {pred4.shape} {pred4.dtype}")
    if not np.isfinite(pred4).all():
        fail("N=4 output not finite")
    # Rows are independent: row i of a batch equals that row run alone. Tolerance 1e-4 relative
    # to the output scale: batched MatMul/Conv kernels may sum in another order (float32).
    scale = float(np.abs(pred4).max()) + 1e-6
    for i in range(4):
        (p1,) = sess.run(["pred"], {k: v[i:i + 1] for k, v in feeds4.items()})
        if p1.shape != (1, C.WINDOW_FRAMES, C.DIM) or not np.isfinite(p1).all():
            fail(f"N=1 output {p1.shape} finite={np.isfinite(p1).all()}")
        err = float(np.abs(p1[0] - pred4[i]).max())
        if err > 1e-4 * scale:
            fail(f"row {i} alone differs from the batch by {err} (scale {scale})")
    # cond = 0 must ignore the music entirely (the null conditioning).
    f0 = dict(feeds4, cond=np.zeros(4, np.float32))
    (a,) = sess.run(["pred"], f0)
    (b,) = sess.run(["pred"], dict(f0, music=(f0["music"][::-1].copy())))
    # Also quiet music, and music whose level jumps inside a window (packages that weigh their
    # candidates by loudness must not do so without music).
    jump = f0["music"] - 60.0
    jump[:, C.MUSIC_FRAMES // 4:] += 60.0
    (c,) = sess.run(["pred"], dict(f0, music=f0["music"] - 60.0))
    (d,) = sess.run(["pred"], dict(f0, music=jump))
    if not (np.array_equal(a, b) and np.array_equal(a, c) and np.array_equal(a, d)):
        fail("cond=0 output depends on the music")
    # cond = 1 must listen to it (t = 999: high noise, where the exemplar's music term matters).
    f1 = dict(feeds4, cond=np.ones(4, np.float32), t=np.full(4, C.TRAIN_STEPS - 1, np.int64))
    mus = np.zeros_like(f1["music"])
    ramp = np.linspace(-40.0, 20.0, C.MUSIC_FRAMES, dtype=np.float32)[:, None]
    mus[:] = ramp  # a crescendo
    (c1,) = sess.run(["pred"], dict(f1, music=mus))
    (c2,) = sess.run(["pred"], dict(f1, music=mus[:, ::-1].copy()))  # a decrescendo
    if music_matters and np.array_equal(c1, c2):
        fail("cond=1 output ignores the music")
    if not music_matters and not np.array_equal(c1, c2):
        fail("a one-exemplar package must ignore the music (softmax over one logit)")
    print(f"ok  {pkg}: names/dtypes match the manifest; N=1 and N=4 shapes, finiteness, "
          f"row independence; cond=0 ignores music, cond=1 "
          f"{'uses it' if music_matters else 'cannot change a single exemplar'}")


def click_music(bpm: float, first_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(157, 80) log-mel dB of a click track, and the click times (s).

    An impulse at time c is inside every centred STFT frame i with |i hop - c sr| <= n_fft / 2
    (librosa center=True), so it raises those frames from -60 dB to 0 dB.
    """
    clicks = first_s + np.arange(0.0, 5.0, 60.0 / bpm)
    centres = np.arange(C.MUSIC_FRAMES) * C.HOP
    on = (np.abs(centres[:, None] - clicks[None] * C.SAMPLE_RATE) <= C.N_FFT / 2).any(axis=1)
    mel = np.where(on[:, None], 0.0, -60.0) - 0.1 * np.arange(C.N_MELS)[None]
    return mel.astype(np.float32), clicks[clicks < 5.0]


def bas_music_beats_60(music_beats_s: np.ndarray, motion_beats_60: np.ndarray) -> float:
    """Bailando's BA at 60 fps (utils/beat_align_score.py:51-55, sigma 3 frames)."""
    d = np.abs(np.round(music_beats_s * 60.0)[:, None] - motion_beats_60[None]).min(axis=1)
    return float(np.exp(-d ** 2 / (2 * 3.0 ** 2)).mean())


def check_exemplar(pkg: Path, m: dict, sess) -> int:
    """x0 recovered from pred is a beat-warped candidate, computed independently in numpy."""
    joints = np.load(SOURCE_DIR / pkg_exemplar.SOURCE_NPY, allow_pickle=False)
    mean = np.asarray(m["motion"]["mean"], np.float64)
    std = np.asarray(m["motion"]["std"], np.float64)
    period, offset = pkg_exemplar.beat_grid(joints)
    table = pkg_exemplar.loop_table(pkg_exemplar.retime_to_grid(joints, period, offset), mean, std)
    k_all = pkg_exemplar.n_candidates(joints.shape[0], period)
    ab = C.alphas_cumprod()
    rng = np.random.default_rng(7)

    def x0_of(feeds):
        (pred,) = sess.run(["pred"], feeds)
        t = feeds["t"]
        return ((feeds["x_t"].astype(np.float64) - np.sqrt(1.0 - ab[t])[:, None, None] * pred)
                / np.sqrt(ab[t])[:, None, None])

    # Does this package hold one candidate? With K=1 x0_hat is the loop from beat 0 at its own
    # tempo for ANY x_t and music.
    feeds = random_inputs(rng, 4)
    feeds["t"] = np.array([0, 1, 500, 999], np.int64)
    own = pkg_exemplar.warped_candidates(table, offset, period, 1, 1.0, 0.0)[0]
    err_first = np.abs(x0_of(feeds) - own).max(axis=(1, 2))
    # Tolerance: pred carries float32 rounding of (x_t - sab x0)/s1, i.e. ~1e-7 * |x_t| / s1
    # (s1 >= 0.01); multiplied back by s1 and divided by sab (>= 0.0064 at t=999) gives
    # ~1e-7 * 4 / 0.0064 ~ 1e-4; 2e-3 leaves margin for the float32 interpolation of the table.
    if (err_first < 2e-3).all():
        print(f"ok  {pkg}: K=1 oracle, x0 from pred equals the loop from beat 0 for random x_t and music "
              f"at t=0,1,500,999 (max err {err_first.max():.2e})")
        return 1
    # K>1: click tracks at three tempos plus random music. x_t drawn near candidate j of the best
    # and of the last tempo group (numpy: choose_warps + warped_candidates) at small t -> the
    # posterior collapses onto it.
    tracks = [click_music(bpm, first) for bpm, first in ((90.0, 0.21), (137.0, 0.4), (70.0, 0.05))]
    music = np.stack([mel for mel, _ in tracks] + [feeds["music"][0]])
    groups = pkg_exemplar.choose_warps(music, period)

    def candidates(w):
        return pkg_exemplar.warped_candidates(table, offset, w["start_step"], k_all, w["rate"], w["phase"])

    for row, row_groups in enumerate(groups):
        for g in (0, len(row_groups) - 1):
            cands = candidates(row_groups[g])
            for j in (0, k_all // 2, k_all - 1):
                tt = np.array([0, 10, 50], np.int64)
                noise = rng.standard_normal((3, C.WINDOW_FRAMES, C.DIM))
                xt = np.sqrt(ab[tt])[:, None, None] * cands[j] + np.sqrt(1.0 - ab[tt])[:, None, None] * noise
                f = {"x_t": xt.astype(np.float32), "t": tt, "music": np.repeat(music[row:row + 1], 3, axis=0),
                     "cond": np.ones(3, np.float32)}
                e = np.abs(x0_of(f) - cands[j]).max()
                if e > 2e-3:
                    fail(f"music row {row}: x_t near candidate {j} of tempo group {g} at small t gives x0 "
                         f"off by {e}")
    # The point of the warp: on a click track the candidates' kinematic beats meet the clicks.
    # Bailando's BA at 60 fps over the clicks (chance ~0.15). At 90 and 70 BPM (slower than
    # 60 / HALF_TIME_BELOW_S) the dance meets every click: at least 0.8 (measured 0.99, 0.89;
    # a beat off by 2 frames at 60 fps still scores 0.8). At 137 BPM it meets every second
    # click, which caps BA near 0.5: at least 0.4 (measured 0.48).
    report = []
    for row, ((_, clicks), least) in enumerate(zip(tracks, (0.8, 0.4, 0.8))):
        best = groups[row][0]
        cand = candidates(best)[0]
        beats = pkg_exemplar.kinematic_beats_60(C.features_to_joints(cand * std + mean))
        inside = clicks[(clicks > 0.25) & (clicks < 4.75)]  # away from the smoothing's edges
        score = bas_music_beats_60(inside, beats)
        report.append(f"{60.0 / best['period_s']:.0f} BPM found in {[90, 137, 70][row]} BPM clicks, "
                      f"dance x{best['rate']:.2f}: BA {score:.2f}")
        if score < least:
            fail(f"click track {row}: the warped dance's kinematic beats miss the clicks (BA {score:.2f} < {least})")
    print(f"ok  {pkg}: {pkg_exemplar.TEMPO_GROUPS} tempo groups x K={k_all} beat-warped candidates; x_t near "
          f"candidate 0/{k_all // 2}/{k_all - 1} of the first and last group at t=0,10,50 denoises to the numpy "
          f"reference (max err < 2e-3) on 4 songs; {'; '.join(report)}")
    return k_all


def cmd_check(pkg: Path, library_source: Path = LIBRARY_SOURCE) -> None:
    import onnx

    m = load_manifest(pkg)
    if m.get("task") == "style-transfer":
        check_style(pkg, m)
        return
    sess = session(pkg, m)
    model = onnx.load(str(pkg / m["components"]["denoiser"]["file"]))
    onnx.checker.check_model(model, full_check=True)
    opsets = {o.domain: o.version for o in model.opset_import}
    if opsets.get("", opsets.get("ai.onnx")) != C.OPSET:
        fail(f"default-domain opset {opsets}, expected {C.OPSET}")
    k = check_exemplar(pkg, m, sess) if m["name"] == "exemplar" else None
    if m["name"] == "library":
        import pkg_library

        pkg_library.check(pkg, m, sess, library_source)
    check_contract(pkg, m, sess, music_matters=k != 1)


def check_style(pkg: Path, m: dict) -> None:
    import onnx

    import pkg_style_common

    for comp in m["components"].values():
        model = onnx.load(str(pkg / comp["file"]))
        onnx.checker.check_model(model, full_check=True)
        opsets = {o.domain: o.version for o in model.opset_import}
        if opsets.get("", opsets.get("ai.onnx")) != C.OPSET:
            fail(f"{comp['file']}: default-domain opset {opsets}, expected {C.OPSET}")
    sess = pkg_style_common.sessions(pkg, m)
    pkg_style_common.check_contract(pkg, m, sess)
    if m["name"].startswith("style-gaussian"):
        import pkg_style_gaussian

        pkg_style_gaussian.check(pkg, m, sess)
    elif m["name"] == "mcm-ldm-ref":
        import pkg_mcm_ldm

        pkg_mcm_ldm.check(pkg, m, sess)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("source", help="derive exemplar-source/aistpp_fixture_joints30.npy from the AIST++ .pkl")
    s.add_argument("--pkl", type=Path, default=DEFAULT_PKL)
    ls = sub.add_parser("library-source", help="derive library-source/: the dance library on one SMPL-24 body "
                                               "(needs ../shared and a built choreod)")
    ls.add_argument("--shared", type=Path, default=SHARED, help="the shared data directory (default ../shared)")
    ls.add_argument("--choreod", type=Path, default=HERE.parent.parent / "target" / "release" / "choreod",
                    help="choreod binary that reads the BVHs (default target/release/choreod)")
    ls.add_argument("--out", type=Path, default=HERE / "library-source")
    e = sub.add_parser("exemplar", help="build the exemplar package")
    e.add_argument("--out", type=Path, required=True)
    e.add_argument("--exemplars", type=int,
                   help="K candidates, one per kinematic beat of the loop (1..12); default: all 12")
    e.add_argument("--second-half-weight", type=float, default=pkg_exemplar.SECOND_HALF_WEIGHT,
                   help="weight of frames 75..149 in the posterior distance (default "
                        f"{pkg_exemplar.SECOND_HALF_WEIGHT}; 1 = whole-window posterior)")
    e.add_argument("--check", action="store_true", help="validate the package after building")
    lb = sub.add_parser("library", help="build the library package (the default)")
    lb.add_argument("--out", type=Path, required=True)
    lb.add_argument("--source", type=Path, default=LIBRARY_SOURCE,
                    help="library source: clips.json and one (T, 24, 3) .npy per clip (default: library-source/)")
    lb.add_argument("--check", action="store_true")
    r = sub.add_parser("mofusion-ref", help="build the MoFusion-architecture package (random weights)")
    r.add_argument("--out", type=Path, required=True)
    r.add_argument("--size", choices=["tiny", "paper"], default="tiny")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--check", action="store_true")
    g = sub.add_parser("style-gaussian", help="build the closed-form Gaussian style-transfer package")
    g.add_argument("--out", type=Path, required=True)
    g.add_argument("--rho", type=float, choices=[0.0, 1.0], default=1.0,
                   help="content-output correlation of the prior: 1 = the default package, 0 = the oracle")
    g.add_argument("--check", action="store_true")
    mc = sub.add_parser("mcm-ldm-ref", help="build the MCM-LDM-architecture package (random weights)")
    mc.add_argument("--out", type=Path, required=True)
    mc.add_argument("--size", choices=["tiny", "paper"], default="tiny")
    mc.add_argument("--seed", type=int, default=0)
    mc.add_argument("--check", action="store_true")
    c = sub.add_parser("check", help="validate a built package with onnxruntime")
    c.add_argument("dir", type=Path)
    a = ap.parse_args()

    if a.cmd == "source":
        SOURCE_DIR.mkdir(exist_ok=True)
        out = SOURCE_DIR / pkg_exemplar.SOURCE_NPY
        j, info = pkg_exemplar.derive_source(a.pkl, out)
        print(f"wrote {out.relative_to(HERE.parent.parent)} {j.shape} sha256 {C.sha256_file(out)} {info}")
    elif a.cmd == "library-source":
        import pkg_library_source

        records = pkg_library_source.build(a.out, a.shared, a.choreod)
        seconds = sum(r["seconds"] for r in records)
        digest = hashlib.sha256()
        for f in sorted(a.out.glob("*.npy")) + [a.out / "clips.json"]:
            digest.update(f.name.encode() + b"\0" + f.read_bytes())
        print(f"wrote {len(records)} clips ({seconds / 60:.2f} min) to {a.out}; sha256 of the .npy files and "
              f"clips.json: {digest.hexdigest()}")
    elif a.cmd == "exemplar":
        k = pkg_exemplar.build(a.out, SOURCE_DIR / pkg_exemplar.SOURCE_NPY, a.exemplars,
                               a.second_half_weight)
        print(f"built exemplar (K={k}) in {a.out}: denoiser.onnx sha256 "
              f"{C.sha256_file(a.out / 'denoiser.onnx')}")
        if a.check:
            cmd_check(a.out)
    elif a.cmd == "library":
        import pkg_library

        info = pkg_library.build(a.out, a.source)
        print(f"built library in {a.out}: {info}; denoiser.onnx sha256 {C.sha256_file(a.out / 'denoiser.onnx')}")
        if a.check:
            cmd_check(a.out, a.source)
    elif a.cmd == "mofusion-ref":
        import pkg_mofusion

        info = pkg_mofusion.build(a.out, a.size, a.seed)
        print(f"built mofusion-ref ({a.size}) in {a.out}: {info['params']:,} parameters, "
              f"{info['flops'] / 1e9:.3f} GFLOPs per evaluation at N=1; denoiser.onnx sha256 "
              f"{C.sha256_file(a.out / 'denoiser.onnx')}")
        if a.check:
            cmd_check(a.out)
    elif a.cmd == "style-gaussian":
        import pkg_style_gaussian

        name = pkg_style_gaussian.build(a.out, a.rho)
        print(f"built {name} in {a.out}")
        if a.check:
            cmd_check(a.out)
    elif a.cmd == "mcm-ldm-ref":
        import pkg_mcm_ldm

        info = pkg_mcm_ldm.build(a.out, a.size, a.seed)
        print(f"built mcm-ldm-ref ({a.size}) in {a.out}: {info}")
        if a.check:
            cmd_check(a.out)
    elif a.cmd == "check":
        cmd_check(a.dir)


if __name__ == "__main__":
    main()
