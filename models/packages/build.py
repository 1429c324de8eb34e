#!/usr/bin/env python3
"""Build and check choreod's shipped model packages (reproducible byte for byte).

    python models/packages/build.py source                      # re-derive exemplar-source/*.npy
    python models/packages/build.py exemplar --out models/packages/exemplar [--exemplars K] [--check]
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
import sys
import tomllib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import pkg_common as C  # noqa: E402
import pkg_exemplar  # noqa: E402

SOURCE_DIR = HERE / "exemplar-source"
DEFAULT_PKL = HERE.parent.parent.parent / "shared" / "fixtures" / "motion" / "aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"


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
    if not np.array_equal(a, b):
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


def check_exemplar(pkg: Path, m: dict, sess) -> int:
    """x0 recovered from pred equals the exemplar: exactly (K=1) / nearest (K>1) at small t."""
    joints = np.load(SOURCE_DIR / pkg_exemplar.SOURCE_NPY, allow_pickle=False)
    mean = np.asarray(m["motion"]["mean"], np.float64)
    std = np.asarray(m["motion"]["std"], np.float64)
    ab = C.alphas_cumprod()
    rng = np.random.default_rng(7)
    k_all = pkg_exemplar.n_exemplars(joints)
    ex = (pkg_exemplar.exemplar_windows(joints, k_all) - mean) / std
    # Does this package hold one exemplar? With K=1 x0_hat is the first window for ANY x_t.
    feeds = random_inputs(rng, 4)
    feeds["t"] = np.array([0, 1, 500, 999], np.int64)
    (pred,) = sess.run(["pred"], feeds)
    t = feeds["t"]
    sab = np.sqrt(ab[t])[:, None, None]
    s1 = np.sqrt(1.0 - ab[t])[:, None, None]
    x0 = (feeds["x_t"].astype(np.float64) - s1 * pred.astype(np.float64)) / sab
    err_first = np.abs(x0 - ex[0]).max(axis=(1, 2))
    # Tolerance: pred carries float32 rounding of (x_t - sab x0)/s1, i.e. ~1e-7 * |x_t| / s1
    # (s1 >= 0.01); multiplied back by s1 and divided by sab (>= 0.0064 at t=999) gives
    # ~1e-7 * 4 / 0.0064 ~ 1e-4; 2e-3 leaves margin for the exemplar table's own rounding.
    single = bool((err_first < 2e-3).all())
    if single:
        print(f"ok  {pkg}: K=1 oracle, x0 from pred equals exemplar 0 for random x_t at t=0,1,500,999 "
              f"(max err {err_first.max():.2e})")
        return 1
    # K>1: x_t drawn near exemplar j at small t -> the posterior collapses onto e_j.
    for j in (0, k_all // 2, k_all - 1):
        tt = np.array([0, 10, 50], np.int64)
        noise = rng.standard_normal((3, C.WINDOW_FRAMES, C.DIM))
        xt = np.sqrt(ab[tt])[:, None, None] * ex[j] + np.sqrt(1.0 - ab[tt])[:, None, None] * noise
        f = {"x_t": xt.astype(np.float32), "t": tt, "music": feeds["music"][:3], "cond": np.ones(3, np.float32)}
        (p,) = sess.run(["pred"], f)
        x0 = (xt - np.sqrt(1.0 - ab[tt])[:, None, None] * p) / np.sqrt(ab[tt])[:, None, None]
        e = np.abs(x0 - ex[j]).max()
        if e > 2e-3:
            fail(f"x_t near exemplar {j} at small t gives x0 off by {e}")
    print(f"ok  {pkg}: K={k_all} exemplars, x_t near exemplar 0/{k_all // 2}/{k_all - 1} at t=0,10,50 "
          f"denoises to it (max err < 2e-3)")
    return k_all


def cmd_check(pkg: Path) -> None:
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
    e = sub.add_parser("exemplar", help="build the exemplar package")
    e.add_argument("--out", type=Path, required=True)
    e.add_argument("--exemplars", type=int, help="K windows (1..18); default: all 18 (the whole loop)")
    e.add_argument("--music-weight", type=float, default=pkg_exemplar.MUSIC_LAMBDA,
                   help=f"lambda on the music cosine logit (default {pkg_exemplar.MUSIC_LAMBDA})")
    e.add_argument("--second-half-weight", type=float, default=pkg_exemplar.SECOND_HALF_WEIGHT,
                   help="weight of frames 75..149 in the posterior distance (default "
                        f"{pkg_exemplar.SECOND_HALF_WEIGHT}; 1 = whole-window posterior)")
    e.add_argument("--check", action="store_true", help="validate the package after building")
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
    elif a.cmd == "exemplar":
        k = pkg_exemplar.build(a.out, SOURCE_DIR / pkg_exemplar.SOURCE_NPY, a.exemplars, a.music_weight,
                               a.second_half_weight)
        print(f"built exemplar (K={k}) in {a.out}: denoiser.onnx sha256 "
              f"{C.sha256_file(a.out / 'denoiser.onnx')}")
        if a.check:
            cmd_check(a.out)
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
