"""The `style-gaussian` packages: style transfer by a closed-form Gaussian denoiser (no download).

The latent is the HumanML3D feature vector with the joint positions (ric, dims 4..67) rewritten
as bone vectors, plus each bone's length (284 = 263 + 21 channels per frame, metres, identity
normalisation). The style encoder emits per-channel statistics of a motion's valid frames; the
denoiser is the optimal (posterior-mean) denoiser of a per-channel Gaussian built from them; the
VAE decoder rebuilds joint positions from bone directions and the content's own bone lengths.
Only the upper-body bone channels are ever changed; everything else is passed through. The
closed form of what inversion + denoising does is in README.md (written by `readme_text`).

`rho` (build option) is the correlation between content and output in the prior:
  rho = 1 (`style-gaussian`, the default package): the prior is a point mass at the
          statistics-transferred content, so transfer and inversion modes both return the
          closed-form map exactly, whatever the noise and the number of steps;
  rho = 0 (`style-gaussian-oracle`): the prior is the style's marginal Gaussian, so DDIM
          inversion + denoising reaches the closed-form map only as steps grow: an oracle for
          the inversion sampler (transfer mode then draws white noise per frame: not for users).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

import pkg_common as C
import pkg_style_common as S
from pkg_mofusion import Builder

# t2m-22 parents (EricGuo5513/HumanML3D paramUtil.py t2m_kinematic_chain; = SMPL's first 22).
PARENTS = C.SMPL_PARENTS[:22]
BONES = 21  # one per non-root joint
LATENT = S.DIM + BONES  # 263 features (ric slots hold bone vectors) + 21 bone lengths
STYLE = 2 * LATENT + 1  # [mean (284), std (284), present flag]
RIC = (4, 4 + 3 * BONES)  # ric positions of joints 1..21 (motion_representation.ipynb layout)
# Upper-body joints whose bones are restyled: spine1-3, neck, collars, head, shoulders,
# elbows, wrists (t2m order). Hips, knees, ankles and feet are passed through so the feet keep
# the content's floor contacts and the pelvis height (dim 3) stays the content's.
UPPER_BODY = [3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21]
# Std floor (metres, in quadrature): a bone component that barely moves in the content (std
# ~0) would otherwise get an unbounded gain s_style / s_content and amplify its jitter. With
# 1 cm the bundled CMU content's neck wobble was amplified ~10x by the AIST++ style (the head
# flopped); 5 cm caps the gain of a still bone at sqrt(s_s^2 + 5^2) / 5 (2.2 for s_s = 10 cm)
# and still lets moving bones (std 10-30 cm) take most of the style's amplitude.
STD_FLOOR = 0.05
# Bone channels are stored in decimetres (x10): typical movement then has a std of order 1 in
# the latent, the noise scale DDIM is built for. In metres (std ~0.01-0.1 against unit noise)
# the signal only emerges in the last few of 1000 timesteps and DDIM inversion converges slowly
# with the number of steps. The map itself is the same in any unit (it is affine-equivariant).
BONE_SCALE = 10.0


def transferable_mask() -> np.ndarray:
    m = np.zeros(LATENT, np.float32)
    for j in UPPER_BODY:
        m[RIC[0] + 3 * (j - 1): RIC[0] + 3 * j] = 1.0
    return m


def ancestor_matrix() -> np.ndarray:
    """A[j-1, k-1] = 1 when bone k lies on the path from the pelvis to joint j (k, j >= 1), so
    position_j - pelvis = sum_k A[j-1, k-1] * bone_k."""
    a = np.zeros((BONES, BONES), np.float32)
    for j in range(1, 22):
        k = j
        while k > 0:
            a[j - 1, k - 1] = 1.0
            k = PARENTS[k]
    return a


class G(Builder):
    """Builder with the few tensor helpers these graphs need (layout [N, T, C])."""

    def cols(self, x: str, a: int, b: int) -> str:
        return self.op("Slice", [x, self.ints([a]), self.ints([b]), self.ints([-1])])

    def masked_stats(self, x: str, mask: str) -> tuple[str, str]:
        """Mean and (population) std over valid frames: [N, 1, C] each."""
        m3 = self.op("Unsqueeze", [mask, self.ints([2])])
        cnt = self.op("Max", [self.op("ReduceSum", [m3, self.ints([1])], keepdims=1),
                              self.const("one", np.array(1.0, np.float32), False)])
        mean = self.op("Div", [self.op("ReduceSum", [self.op("Mul", [x, m3]), self.ints([1])], keepdims=1), cnt])
        d = self.op("Sub", [x, mean])
        var = self.op("Div", [self.op("ReduceSum", [self.op("Mul", [self.op("Mul", [d, d]), m3]), self.ints([1])],
                                      keepdims=1), cnt])
        return mean, self.op("Sqrt", [var])

    def features_to_latent(self, f: str) -> str:
        """[N,T,263] (metres) -> [N,T,284]: ric slots become bone vectors, lengths appended."""
        ric = self.op("Reshape", [self.cols(f, *RIC), self.ints([0, 0, BONES, 3])])
        zero = self.op("Mul", [self.cols(f, 3, 4), self.const("zero", np.array(0.0, np.float32), False)])
        pelvis = self.op("Unsqueeze", [self.op("Concat", [zero, self.cols(f, 3, 4), zero], axis=-1),
                                       self.ints([2])])                       # (0, root_y, 0)
        joints = self.op("Concat", [pelvis, ric], axis=2)                      # [N,T,22,3]
        parents = self.op("Gather", [joints, self.ints(PARENTS[1:])], axis=2)
        bones = self.op("Sub", [ric, parents])                                  # [N,T,21,3]
        lengths = self.op("Sqrt", [self.op("ReduceSum", [self.op("Mul", [bones, bones]), self.ints([3])],
                                           keepdims=0)])
        flat = self.op("Reshape", [bones, self.ints([0, 0, 3 * BONES])])
        scale = self.const("bone_scale", np.array(BONE_SCALE, np.float32), False)
        return self.op("Concat", [self.cols(f, 0, RIC[0]), self.op("Mul", [flat, scale]), self.cols(f, RIC[1], S.DIM),
                                  self.op("Mul", [lengths, scale])], axis=-1)


def io(name: str, shape, int64: bool = False):
    return helper.make_tensor_value_info(name, TensorProto.INT64 if int64 else TensorProto.FLOAT, shape)


def finish(b: G, name: str, out: str, out_name: str, inputs, out_shape, doc: str) -> onnx.ModelProto:
    b.nodes.append(helper.make_node("Identity", [out], [out_name], name=out_name))
    graph = helper.make_graph(b.nodes, name, inputs=inputs, outputs=[io(out_name, out_shape)], initializer=b.inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", C.OPSET)])
    model.ir_version = 10
    model.doc_string = doc
    return model


def vae_encoder() -> onnx.ModelProto:
    b = G(0)
    lat = b.features_to_latent("features")
    lat = b.op("Mul", [lat, b.op("Unsqueeze", ["mask", b.ints([2])])])
    return finish(b, "style_gaussian_vae_encoder", lat, "latent",
                  [io("features", ["N", "T", S.DIM]), io("mask", ["N", "T"])], ["N", "T", LATENT],
                  "HumanML3D features -> bone-vector latent (deterministic, no weights)")


def vae_decoder() -> onnx.ModelProto:
    b = G(0)
    lat = "latent"
    bones = b.op("Reshape", [b.cols(lat, *RIC), b.ints([0, 0, BONES, 3])])
    norm = b.op("Sqrt", [b.op("Add", [b.op("ReduceSum", [b.op("Mul", [bones, bones]), b.ints([3])], keepdims=1),
                                      b.const("tiny", np.array(1e-12, np.float32), False)])])
    lengths = b.op("Unsqueeze", [b.op("Div", [b.cols(lat, S.DIM, LATENT),
                                               b.const("bone_scale", np.array(BONE_SCALE, np.float32), False)]),
                                 b.ints([3])])
    scaled = b.op("Mul", [b.op("Div", [bones, norm]), lengths])                 # content's lengths
    # positions relative to the pelvis: A @ bones along the joint axis
    rel = b.op("MatMul", [b.const("ancestors", ancestor_matrix(), False), scaled])
    root_y = b.cols(lat, 3, 4)
    zero = b.op("Mul", [root_y, b.const("zero", np.array(0.0, np.float32), False)])
    pelvis = b.op("Unsqueeze", [b.op("Concat", [zero, root_y, zero], axis=-1), b.ints([2])])
    ric = b.op("Reshape", [b.op("Add", [rel, pelvis]), b.ints([0, 0, 3 * BONES])])
    f = b.op("Concat", [b.cols(lat, 0, RIC[0]), ric, b.cols(lat, RIC[1], S.DIM)], axis=-1)
    f = b.op("Mul", [f, b.op("Unsqueeze", ["mask", b.ints([2])])])
    return finish(b, "style_gaussian_vae_decoder", f, "features",
                  [io("latent", ["N", "T", LATENT]), io("mask", ["N", "T"])], ["N", "T", S.DIM],
                  "bone-vector latent -> HumanML3D features: bone directions x the latent's bone lengths")


def style_encoder() -> onnx.ModelProto:
    b = G(0)
    lat = b.features_to_latent("features")
    mean, std = b.masked_stats(lat, "mask")
    one = b.op("Add", [b.op("Mul", [b.cols(b.op("Squeeze", [mean, b.ints([1])]), 0, 1),
                                    b.const("zero", np.array(0.0, np.float32), False)]),
                       b.const("one", np.array(1.0, np.float32), False)])      # [N,1] of ones
    style = b.op("Concat", [b.op("Squeeze", [mean, b.ints([1])]), b.op("Squeeze", [std, b.ints([1])]), one], axis=-1)
    return finish(b, "style_gaussian_style_encoder", style, "style",
                  [io("features", ["N", "T", S.DIM]), io("mask", ["N", "T"])], ["N", STYLE],
                  "per-channel mean and std of the latent over valid frames, then a presence flag 1")


def denoiser(rho: float) -> onnx.ModelProto:
    b = G(0)
    f32 = lambda v: b.const("c", np.asarray(v, np.float32), False)  # noqa: E731
    ab = b.op("Gather", [f32(S.alphas_cumprod()), "t"], axis=0)
    ab = b.op("Unsqueeze", [ab, b.ints([1, 2])])                                 # [N,1,1]
    sab = b.op("Sqrt", [ab])
    one_m = b.op("Sub", [f32(1.0), ab])
    mc, sc = b.masked_stats("content", "mask")                                  # content statistics
    style = b.op("Unsqueeze", ["style", b.ints([1])])                           # [N,1,S]
    ms, ss, present = b.cols(style, 0, LATENT), b.cols(style, LATENT, 2 * LATENT), b.cols(style, 2 * LATENT, STYLE)
    absent = b.op("Sub", [f32(1.0), present])
    m_tgt = b.op("Add", [b.op("Mul", [present, ms]), b.op("Mul", [absent, mc])])  # null style: the content's own
    s_tgt = b.op("Add", [b.op("Mul", [present, ss]), b.op("Mul", [absent, sc])])
    floor2 = f32((STD_FLOOR * BONE_SCALE) ** 2)
    sc_f = b.op("Sqrt", [b.op("Add", [b.op("Mul", [sc, sc]), floor2])])
    st_f = b.op("Sqrt", [b.op("Add", [b.op("Mul", [s_tgt, s_tgt]), floor2])])
    z = b.op("Div", [b.op("Sub", ["content", mc]), sc_f])
    mu = b.op("Add", [m_tgt, b.op("Mul", [b.op("Mul", [st_f, f32(rho)]), z])])
    var = b.op("Mul", [b.op("Mul", [st_f, st_f]), f32(1.0 - rho * rho)])
    # passed-through channels: a point mass at the trajectory (dims 0..3) or the content
    base = b.op("Concat", ["trajectory", b.cols("content", S.TRAJ_DIMS, LATENT)], axis=-1)
    tm = f32(transferable_mask())
    keep = f32(1.0 - transferable_mask())
    mu = b.op("Add", [b.op("Mul", [tm, mu]), b.op("Mul", [keep, base])])
    var = b.op("Mul", [tm, var])
    # posterior mean of x0 ~ N(mu, var) given x_t = sqrt(ab) x0 + sqrt(1 - ab) eps
    resid = b.op("Sub", ["x_t", b.op("Mul", [sab, mu])])
    gain = b.op("Div", [b.op("Mul", [sab, var]), b.op("Add", [b.op("Mul", [ab, var]), one_m])])
    x0 = b.op("Add", [mu, b.op("Mul", [gain, resid])])
    eps = b.op("Div", [b.op("Sub", ["x_t", b.op("Mul", [sab, x0])]), b.op("Sqrt", [one_m])])
    return finish(b, "style_gaussian_denoiser", eps, "pred",
                  [io("x_t", ["N", "T", LATENT]), io("t", ["N"], int64=True), io("content", ["N", "T", LATENT]),
                   io("trajectory", ["N", "T", S.TRAJ_DIMS]), io("mask", ["N", "T"]), io("style", ["N", STYLE])],
                  ["N", "T", LATENT], f"closed-form Gaussian epsilon denoiser, rho = {rho}")


def build(out_dir: Path, rho: float) -> str:
    out_dir.mkdir(parents=True, exist_ok=True)
    name = "style-gaussian" if rho == 1.0 else "style-gaussian-oracle"
    lat, feat = ["N", "T", LATENT], ["N", "T", S.DIM]
    specs = {
        "vae_encoder": (vae_encoder(), [("features", feat), ("mask", ["N", "T"])], [("latent", lat)]),
        "vae_decoder": (vae_decoder(), [("latent", lat), ("mask", ["N", "T"])], [("features", feat)]),
        "style_encoder": (style_encoder(), [("features", feat), ("mask", ["N", "T"])], [("style", ["N", STYLE])]),
        "denoiser": (denoiser(rho), [("x_t", lat), ("t", ["N"]), ("content", lat),
                                     ("trajectory", ["N", "T", S.TRAJ_DIMS]), ("mask", ["N", "T"]),
                                     ("style", ["N", STYLE])], [("pred", lat)]),
    }
    comps = {}
    for role, (model, ins, outs) in specs.items():
        sha = C.save_model(model, out_dir / f"{role}.onnx")
        comps[role] = (f"{role}.onnx", sha, ins, outs)
    desc = (f"Closed-form Gaussian style transfer (rho = {rho:g}): per-channel statistics of the "
            f"style's upper-body bone vectors replace the content's; trajectory, pelvis height, legs, "
            f"feet and bone lengths are the content's. No trained weights, nothing to download.")
    # Identity normalisation: the graphs work in metres (bone geometry needs raw positions).
    S.write_manifest(out_dir, name=name, description=desc, max_frames=MAX_FRAMES,
                     mean=np.zeros(S.DIM), std=np.ones(S.DIM),
                     sampler={"set_alpha_to_one": True, "guidance": 1.0, "content_guidance": 1.0,
                              "style_guidance": 1.0},
                     components=comps,
                     extra_comment="# set_alpha_to_one = true: the last DDIM step returns x0_hat itself, so the\n"
                                   "# passed-through channels come back exactly (alphas_cumprod[0] would leave\n"
                                   "# 2.9 % of the initial noise in them).\n")
    (out_dir / "README.md").write_text(readme_text(name, rho), encoding="utf-8")
    return name


# One statistics map for the whole clip: segments would each get their own map (seams), so the
# limit is only a memory bound (10 min at 20 fps; the latent is 284 floats per frame).
MAX_FRAMES = 12000


def closed_form(content_latent: np.ndarray, content_mask: np.ndarray, style_vec: np.ndarray) -> np.ndarray:
    """The map inversion + denoising converges to (README): numpy, one row [T, 284]."""
    valid = content_mask > 0
    mc = content_latent[valid].mean(axis=0)
    sc = content_latent[valid].std(axis=0)
    ms, ss = style_vec[:LATENT], style_vec[LATENT:2 * LATENT]
    floor = STD_FLOOR * BONE_SCALE
    gain = np.sqrt(ss ** 2 + floor ** 2) / np.sqrt(sc ** 2 + floor ** 2)
    mapped = ms + gain * (content_latent - mc)
    tm = transferable_mask()
    return tm * mapped + (1.0 - tm) * content_latent


def check(pkg: Path, m: dict, sess: dict) -> None:
    """Package-specific checks: encoder/decoder round trip, and the closed form in transfer mode."""
    rng = np.random.default_rng(5)
    feats = joints_like_features(rng, 2, 80)
    mask = np.ones((2, 80), np.float32)
    (lat,) = sess["vae_encoder"].run(None, {"features": feats, "mask": mask})
    (dec,) = sess["vae_decoder"].run(None, {"latent": lat, "mask": mask})
    # Round trip: float32 sqrt/divide on positions of ~1 m: 1e-5 m is ~100 ulps.
    err = float(np.abs(dec - feats).max())
    if err > 1e-5:
        S.fail(f"decoder(encoder(x)) differs from x by {err}")
    # The style vector is [mean, population std, 1] of the latent over valid frames (numpy here).
    half = mask.copy()
    half[1, 50:] = 0.0
    (sv,) = sess["style_encoder"].run(None, {"features": feats, "mask": half})
    for i, n_valid in ((0, 80), (1, 50)):
        v = lat[i, :n_valid]
        want = np.concatenate([v.mean(axis=0), v.std(axis=0), [1.0]])
        # float32 sums over <= 80 frames of values <= ~10: 1e-4 absolute is ~100 ulps.
        if np.abs(sv[i] - want).max() > 1e-4:
            S.fail(f"style_encoder row {i} differs from numpy's mean/std by {np.abs(sv[i] - want).max()}")
    rho = float(m["name"] == "style-gaussian")
    check_posterior(sess, rho, lat[0], sv[1])
    print(f"ok  {pkg}: decode(encode(features)) = features (max err {err:.1e} m); style = [mean, std, 1]; "
          f"x0 from pred = the Gaussian posterior mean at t = 1, 500, 981 (rho = {rho:g})")
    check_closed_form(pkg, rho, feats[0], joints_like_features(np.random.default_rng(6), 1, 60, swing=1.0)[0])


def check_posterior(sess: dict, rho: float, content: np.ndarray, style_vec: np.ndarray) -> None:
    """x0 recovered from pred equals E[x0 | x_t] for x0 ~ N(mu, var) (README), computed in numpy
    float64 from the content statistics and the style vector, for random x_t."""
    rng = np.random.default_rng(8)
    ab = S.alphas_cumprod()
    t = np.array([1, 500, 981], np.int64)
    x_t = rng.standard_normal((3,) + content.shape).astype(np.float32)
    traj = rng.standard_normal((3, len(content), S.TRAJ_DIMS)).astype(np.float32)
    c = content.astype(np.float64)
    mc, sc = c.mean(axis=0), c.std(axis=0)
    ms, ss = style_vec[:LATENT].astype(np.float64), style_vec[LATENT:2 * LATENT].astype(np.float64)
    floor2 = (STD_FLOOR * BONE_SCALE) ** 2
    mu = ms + rho * np.sqrt(ss ** 2 + floor2) * (c - mc) / np.sqrt(sc ** 2 + floor2)
    var = (ss ** 2 + floor2) * (1.0 - rho ** 2) * np.ones_like(c)
    tm = transferable_mask().astype(bool)
    feeds = {"x_t": x_t, "t": t, "content": np.repeat(content[None], 3, axis=0), "trajectory": traj,
             "mask": np.ones((3, len(content)), np.float32), "style": np.repeat(style_vec[None], 3, axis=0)}
    (pred,) = sess["denoiser"].run(None, feeds)
    for i, ti in enumerate(t):
        a = ab[ti]
        x0 = (x_t[i] - np.sqrt(1.0 - a) * pred[i]) / np.sqrt(a)
        m_i = np.where(tm, mu, np.concatenate([traj[i], c[:, S.TRAJ_DIMS:]], axis=1))
        v_i = np.where(tm, var, 0.0)
        want = m_i + np.sqrt(a) * v_i * (x_t[i] - np.sqrt(a) * m_i) / (a * v_i + 1.0 - a)
        # float32 pred carries ~1e-7 relative error of x_t / sqrt(1 - a); multiplied back by
        # sqrt(1 - a) / sqrt(a) (<= 13 at t = 981) on |x_t| <= 5: 1e-4 leaves a 10x margin.
        err = float(np.abs(x0 - want).max())
        if err > 1e-4 * max(1.0, float(np.abs(want).max())):
            S.fail(f"denoiser: x0 from pred at t = {ti} differs from the Gaussian posterior mean by {err}")


def check_closed_form(pkg: Path, rho: float, content: np.ndarray, style: np.ndarray) -> None:
    """The reference loop (stylize_reference.py) against the closed form A(c), decoded."""
    import stylize_reference as R

    p = R.Package(pkg, 2)
    lat = p.run("vae_encoder", {"features": np.where(np.arange(S.DIM) < S.TRAJ_DIMS, 0, content)[None]
                                .astype(np.float32), "mask": np.ones((1, len(content)), np.float32)})[0]
    s = style.copy()
    s[:, :S.TRAJ_DIMS] = 0.0
    sv = p.run("style_encoder", {"features": s[None], "mask": np.ones((1, len(s)), np.float32)})[0]
    mapped = closed_form(lat, np.ones(len(lat)), sv)

    def decoded(latent: np.ndarray) -> np.ndarray:
        f = p.run("vae_decoder", {"latent": latent[None].astype(np.float32),
                                  "mask": np.ones((1, len(lat)), np.float32)})[0]
        f[:, :S.TRAJ_DIMS] = content[:, :S.TRAJ_DIMS]
        return f

    want = decoded(mapped)
    moved = float(np.abs(want - content).max())
    # (mode, steps, guidance g / style weight ws, expected): with rho = 1 the guided x0 is
    # c + g (A(c) - c) on restyled channels in both modes (README), so g = 2 doubles the shift.
    runs = [("transfer", 50, 1.0, want), ("inversion", 30, 1.0, want),
            ("transfer", 50, 2.0, decoded(2.0 * mapped - lat)),
            ("inversion", 30, 2.0, decoded(2.0 * mapped - lat))] if rho == 1.0 else \
        [("inversion", 30, 1.0, want), ("inversion", 200, 1.0, want)]
    errs = []
    for mode, steps, g, expected in runs:
        out = R.stylize(p, content, style, mode, g, 1.0, g, steps, None, 0)
        errs.append(float(np.sqrt(((out - expected) ** 2).mean())))
    # Properties independent of the closed form, on the last run's output: legs, feet, pelvis
    # height and trajectory are the content's, every bone keeps its length (float32 on ~1 m).
    legs = [j for j in range(1, 22) if j not in UPPER_BODY]
    ric_out = out[:, RIC[0]:RIC[1]].reshape(-1, BONES, 3)
    ric_in = content[:, RIC[0]:RIC[1]].reshape(-1, BONES, 3)
    leg_err = float(np.abs(ric_out[:, [j - 1 for j in legs]] - ric_in[:, [j - 1 for j in legs]]).max())
    root_err = float(np.abs(out[:, :4] - content[:, :4]).max())

    def bone_lengths(f: np.ndarray) -> np.ndarray:
        j = np.concatenate([np.stack([np.zeros(len(f)), f[:, 3], np.zeros(len(f))], axis=1)[:, None],
                            f[:, RIC[0]:RIC[1]].reshape(-1, BONES, 3)], axis=1)
        return np.linalg.norm(j[:, 1:] - j[:, PARENTS[1:]], axis=-1)

    len_err = float(np.abs(bone_lengths(out) - bone_lengths(content)).max())
    if max(leg_err, root_err, len_err) > 1e-5:
        S.fail(f"legs moved {leg_err} m, root features {root_err}, bone lengths {len_err} m")
    if rho == 1.0:
        # Exact up to float32 rounding of metres-scale positions (~1e-7 per op, a few dozen ops).
        if max(errs) > 1e-5:
            S.fail(f"rho=1: transfer/inversion (g = 1, 2) differ from the closed form by RMS {errs}")
    elif not errs[1] < 0.5 * errs[0] < 0.5 * moved:
        # DDIM's discretisation error must shrink with steps and stay well under the change itself.
        S.fail(f"rho=0: RMS to the closed form {errs} (30, 200 steps) does not shrink (change {moved})")
    print(f"ok  {pkg}: stylize_reference.py vs the closed form, RMS {', '.join(f'{e:.1e}' for e in errs)} m "
          f"({', '.join(f'{mo} {st} steps g={g:g}' for mo, st, g, _ in runs)}; the map moves joints by up to "
          f"{moved:.3f} m)")


def joints_like_features(rng: np.random.Generator, n: int, t: int, swing: float = 0.3) -> np.ndarray:
    """Features whose ric slots hold a real skeleton (SMPL rest bones, each bone swinging about
    the vertical by `swing` radians), the rest noise."""
    f = S.random_motion(rng, n, t)
    f[..., :S.TRAJ_DIMS] = 0.0
    f[..., 3] = 0.9 + 0.05 * f[..., 3]
    phase = np.linspace(0, 4 * np.pi, t)[None, :, None]
    joints = np.zeros((n, t, 22, 3))
    joints[:, :, 0, 1] = f[..., 3]
    for j in range(1, 22):
        angle = swing * np.sin(phase + j)[..., 0]
        off = C.SMPL_OFFSETS[j]
        rot = np.stack([off[0] * np.cos(angle) - off[2] * np.sin(angle), np.full_like(angle, off[1]),
                        off[0] * np.sin(angle) + off[2] * np.cos(angle)], axis=-1)
        joints[:, :, j] = joints[:, :, PARENTS[j]] + rot
    f[..., RIC[0]:RIC[1]] = joints[:, :, 1:].reshape(n, t, -1)
    return f.astype(np.float32)


def readme_text(name: str, rho: float) -> str:
    return README.format(name=name, rho=f"{rho:g}", floor_latent=STD_FLOOR * BONE_SCALE,
                         floor_cm=STD_FLOOR * 100, scale=BONE_SCALE, latent=LATENT, style=STYLE,
                         upper=", ".join(map(str, UPPER_BODY)), max_frames=MAX_FRAMES)


README = """# `{name}` — closed-form Gaussian style transfer (rho = {rho})

Built by `models/packages/build.py style-gaussian --rho {rho}`. No trained weights and nothing
to download: four small ONNX graphs that compute statistics and a closed-form denoiser. It
follows the style-transfer contract (models/packages/README.md) so `choreod stylize` runs it
with the same sampling loop as `mcm-ldm-ref`.

## What it transfers, and what it cannot

It moves the **upper body's posture and movement amplitude** of the content towards the
style's: per bone of the spine, neck, head, collars, arms (t2m joints {upper}), each component
of the bone vector (in the root-facing frame) gets the style's mean and standard deviation over
its frames — arms held higher or lower, a forward lean, wider or smaller arm swings. Timing,
rhythm and everything else come from the content. It **keeps exactly**: the root trajectory
(dims 0..3 come from the trajectory condition), the pelvis height (dim 3), legs and feet (hips,
knees, ankles, toes: so the feet touch the floor where the content's did, and the foot contact
labels stay true), and every bone length (the decoder puts unit bone directions back together
with the content's own lengths, carried in 21 extra latent channels). Measured on the bundled
motions (content `cmu_01_01_8s_30fps.bvh`, style the AIST++ `.pkl`, both converted to t2m-22
features at 20 fps with choreod; CMU joints mapped by name): root path within 4 µm, bone
lengths within 3e-7 m, legs and feet within 4 µm of the content, both modes equal within
1e-6; the wrists ride 0.21 m above the pelvis on average instead of 0.02 m (the dancer's:
0.24 m), their spread (std about the pelvis) grows from 0.12 to 0.17 m (dancer: 0.27 m),
shoulders, elbows and wrists move by 17 cm on average (39 cm at most). Mean bone directions include each source skeleton's **rest
geometry**: SMPL's head joint sits in front of the neck and its collar bones rise, CMU's do
not, so a CMU content with an SMPL style also takes a forward head and raised collars — a
retargeting that maps rotations onto the t2m rest pose (rather than joint directions) avoids
that. It **cannot** transfer
anything temporal (a limp, a rhythm, a gait), leg style, or correlations between joints (each
channel is mapped on its own); a style whose arms barely move gives arms that barely move. The
rot6d (67..193) and local-velocity (193..259) features of the output are the content's: the
joints choreod writes come from dims 0..67 (`recover_from_ric`); recompute features from those
joints if you need all 263 consistent.

## The latent ({latent} channels per frame; manifest mean 0 / std 1, i.e. raw features)

`vae_encoder`: dims 0..4 and 67..263 as given; the ric slots 4..67 hold bone vectors
{scale:g} b_j, b_j = p_j - p_parent(j) (p_0 = (0, root_y, 0), t2m parents), and channels
263..284 hold {scale:g} |b_j| — decimetres, so that moving bones have a std of order 1 against
the unit noise (in metres DDIM inversion converges far more slowly with the steps).
`vae_decoder`: p_j = p_0 + sum over bones k on the path pelvis -> j of L_k b_k / |b_k|, with L_k
from channels 263..284 / {scale:g}. `decode(encode(x)) = x` (float32 rounding) for any skeleton.

## The style vector ({style} floats) and the denoiser

`style_encoder`: style = [m (284), s (284), 1]: mean and population std of the latent over the
valid frames (mask 1), then a presence flag. Null style = zeros (flag 0).

`denoiser` (epsilon prediction). Per channel, with content latent c (dims 0..3 zeroed),
its valid-frame mean m_c and std s_c, and the target statistics (m*, s*) = (m, s) of the style
or, for a null style, (m_c, s_c); floors s~ = sqrt(s^2 + {floor_latent:g}^2) ({floor_cm:g} cm in
latent units, only the restyled channels use them):

    z      = (c - m_c) / s~_c
    mu     = m* + rho * s~* * z,      var = s~*^2 * (1 - rho^2)      (restyled channels)
    mu     = trajectory (dims 0..3) or c,  var = 0                    (all other channels)
    x0_hat = mu + sqrt(ab_t) var (x_t - sqrt(ab_t) mu) / (ab_t var + 1 - ab_t)
    pred   = (x_t - sqrt(ab_t) x0_hat) / sqrt(1 - ab_t)

i.e. the exact posterior mean for x0 ~ N(mu, var), x_t = sqrt(ab_t) x0 + sqrt(1 - ab_t) eps,
ab_t = alphas_cumprod[t] of the scaled-linear schedule (0.00085 -> 0.012, 1000 steps).

## The closed form (for oracle tests)

The map both modes approach, per restyled channel (all others: passed through exactly):

    A(c) = m_s + (s~_s / s~_c) (c - m_c)

- **rho = 1** (`style-gaussian`): var = 0, so x0_hat = mu for every x_t; with the manifest's
  `set_alpha_to_one = true` the last DDIM step returns x0_hat: **transfer mode returns exactly**
  `c + g (A(c) - c)` for guidance g (A(c) at the default g = 1), whatever the initial noise and
  steps (passed-through channels are identical in both guidance rows, so exact for any g).
  Inversion mode returns `wc c + ws (A(c) - c)` on restyled channels (A(c) at wc = ws = 1):
  the unconditional row (content and style zeros) predicts 0 there. It also predicts 0 for
  every passed-through channel but the trajectory, so **wc != 1 scales the content's pelvis
  height, legs and bone lengths by wc: keep wc = 1 with this package** (the manifest's default);
  ws alone sets the strength of the style.
- **rho = 0** (`style-gaussian-oracle`): the content's prior is N(m_c, s~_c^2) and the style's
  N(m_s, s~_s^2), so deterministic DDIM inversion under the content, then DDIM under the style,
  is the probability-flow map between two Gaussians. Its continuous limit, for inversion up to
  the level a_T of the top timestep, is m_s + s~_s (sqrt(a_T) (m_c - m_s) + sqrt(a_T s~_c^2 + 1 -
  a_T) z) / sqrt(a_T s~_s^2 + 1 - a_T) with z = (c - m_c) / s~_c, which is A(c) as a_T -> 0
  (a_T = 0.0075 at 30 steps, 0.0048 at 200: a small residual remains). With finitely many steps every DDIM step is affine per channel. A step from level a
  to level a' with the network evaluated at level e (its timestep's alphas_cumprod) is

      eps = sqrt(1 - e) (x - sqrt(e) mu) / (e var + 1 - e)
      x'  = sqrt(a') (x - sqrt(1 - a) eps) / sqrt(a) + sqrt(1 - a') eps

  with e = a for denoising steps (diffusers DDIMScheduler.step) and e = a' for inversion steps
  (DDIMInverseScheduler.step evaluates the network at the timestep it moves to); a = 1 before
  the first inversion step and a' = 1 after the last denoising step (set_alpha_to_one = true).
  Inversion uses (mu, var) = (m_c, s~_c^2), denoising (m_s, s~_s^2). Composing these steps over
  the sampler's timesteps reproduces stylize_reference.py to 2.4e-7 m (30 and 200 steps, checked);
  the result's distance to A(c) shrinks as the steps grow (RMS 2.1 mm at 30 steps, 0.65 mm at
  200 in `build.py check`).
  Transfer mode with rho = 0 draws white noise per frame around the style's mean: use this
  package only as an oracle.

`max_frames = {max_frames}` (one statistics map per clip; segments would each get their own),
`min_frames = 40` (2 s: statistics of a shorter style are not a style).
"""
