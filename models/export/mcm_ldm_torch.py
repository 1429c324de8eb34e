"""The torch half of the MCM-LDM exporter: the official modules, the ONNX wrappers, the official loop.

Imported only by `mcm_ldm.py` (export, --verify) and `make_test_checkpoints.py`; needs torch,
timm and diffusers (the user's environment, never choreod's). Every network evaluation goes
through the official modules imported from the user's MCM-LDM clone; the wrappers only change
what the official code's hazards require for a graph with dynamic batch and length:

- `vae.encode` samples (`dist.rsample()`, mld_vae.py `encode`): the wrapper returns the posterior
  mean `dist.loc`, so the encoder is deterministic (the demo itself is stochastic twice).
- lengths are Python lists turned into boolean masks by `lengths_to_mask`
  (mld/utils/temos_utils.py:10); traced, they would become constants of the example's length.
  During export `lengths_to_mask` in the VAE and denoiser modules returns the mask tensor the
  wrapper passes in place of the list.
- `.squeeze()` without a dimension on the (1, N, 256) style and trajectory embeddings
  (mld_denoiser.py `forward`, lines 245 and 250) also drops N when N = 1 in eager PyTorch.
  torch.export keeps a dynamic N (it squeezes only axes known to be 1), so the exported denoiser
  runs at N = 1 (--verify checks it against the official batch). `squeeze(d)` of a dynamic axis
  (the VAE decoder's `.squeeze(0)` over frames) is left out during export: ONNX Squeeze would
  fail for every T > 1.
- learned positional tables have 500 rows (`PositionEmbeddingLearned1D(max_len=500)`,
  mld/models/operator/position_encoding.py): the package declares `max_frames` accordingly.
- the MotionCLIP constructor loads CLIP ViT-B/32 (`get_model_and_data`,
  mld/models/motionclip_263/utils/get_model_and_data.py): the encoder module
  `Encoder_TRANSFORMER` is built directly from the official parameter file instead.
"""

from __future__ import annotations

import contextlib
import io
import logging
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
import yaml

import mcm_ldm as E

LATENT_TOKENS = 7  # configs/config_mld_humanml3d.yaml model.latent_dim [7, 256]
LATENT_DIM = 256


class Official:
    """The official modules of one MCM-LDM clone, built from its configuration files."""

    def __init__(self, repo: Path):
        sys.path.insert(0, str(repo))
        from mld.data.humanml.scripts import motion_process
        from mld.models.architectures import mld_denoiser, mld_vae
        from mld.models.motionclip_263.models.architectures import transformer
        from mld.utils import temos_utils

        self.repo = repo
        self.mld_vae, self.mld_denoiser = mld_vae, mld_denoiser
        self.lengths_to_mask = temos_utils.lengths_to_mask
        self.recover_from_ric = motion_process.recover_from_ric
        main = _load_yaml(repo / E.MAIN_CONFIG)
        self.vae = mld_vae.MldVae(**_module_params(repo / E.VAE_CONFIG, main))
        with warnings.catch_warnings():
            # nn.TransformerEncoder's note on its fused path (mld_denoiser.py:29, :196)
            warnings.filterwarnings("ignore", message="enable_nested_tensor is True")
            self.denoiser = mld_denoiser.MldDenoiser(**_module_params(repo / E.DENOISER_CONFIG, main))
        # MotionCLIP: the official code passes the whole parameter file to the constructor
        # (mld/models/motionclip_263/models/get_model.py `get_model`).
        self.motionclip_encoder = transformer.Encoder_TRANSFORMER(**_load_yaml(repo / E.MOTIONCLIP_CONFIG))
        self.scheduler_config = _load_yaml(repo / E.SCHEDULER_CONFIG)["scheduler"]

    def modules(self) -> dict:
        return {"vae": self.vae, "denoiser": self.denoiser, "motionclip_encoder": self.motionclip_encoder}

    def load(self, weights: dict) -> None:
        """Strict load per module; every mismatch becomes one error naming the module."""
        for name, module in self.modules().items():
            sd = {k: torch.as_tensor(v) for k, v in weights[name].items()}
            missing, unexpected = module.load_state_dict(sd, strict=False)
            if missing or unexpected:
                raise E.ExportError(
                    f"{name}: the checkpoint does not fit the official module of this clone "
                    f"(missing {len(missing)} e.g. {missing[:3]}, unexpected {len(unexpected)} e.g. {unexpected[:3]})")
            module.eval()  # dropout off (mld.py only sets the top-level flag: reference-facts §1)

    def state_dicts(self) -> dict:
        return {name: m.state_dict() for name, m in self.modules().items()}


def _load_yaml(path: Path) -> dict:
    with open(path, encoding="utf-8") as f:
        return yaml.safe_load(f)


def _module_params(path: Path, main: dict) -> dict:
    """`params` of a configs/modules/*.yaml file with its `${a.b}` references resolved from the
    main configuration (OmegaConf interpolation, as mld/config.py does), DATASET.NFEATS = 263
    (set at run time from the HumanML3D data module in the official code)."""
    (section,) = _load_yaml(path).values()
    params = dict(section["params"])
    for key, value in params.items():
        if isinstance(value, str) and value.startswith("${") and value.endswith("}"):
            dotted = value[2:-1]
            if dotted == "DATASET.NFEATS":
                params[key] = E.DIM
                continue
            node = main
            for part in dotted.split("."):
                node = node.get(part) if isinstance(node, dict) else None
            params[key] = node
    return params


# --- export ---------------------------------------------------------------------------------

class VaeEncoder(torch.nn.Module):
    def __init__(self, vae):
        super().__init__()
        self.vae = vae

    def forward(self, features, mask):
        _, dist = self.vae.encode(features, mask > 0.5)
        return dist.loc.permute(1, 0, 2)  # (7, N, 256) -> (N, 7, 256): the posterior mean


class VaeDecoder(torch.nn.Module):
    def __init__(self, vae):
        super().__init__()
        self.vae = vae

    def forward(self, latent, mask):
        return self.vae.decode(latent.permute(1, 0, 2), mask > 0.5)


class StyleEncoder(torch.nn.Module):
    def __init__(self, encoder):
        super().__init__()
        self.encoder = encoder

    def forward(self, features, mask):
        x = features.permute(0, 2, 1).unsqueeze(2)  # (N, 263, 1, T), as mld.py `forward` feeds it
        y = torch.zeros(features.shape[0], dtype=torch.int64)
        return self.encoder({"x": x, "y": y, "mask": mask > 0.5})["mu"]


class Denoiser(torch.nn.Module):
    def __init__(self, denoiser):
        super().__init__()
        self.denoiser = denoiser

    def forward(self, x_t, t, content, trajectory, mask, style):
        # encoder_hidden_states order of mld.py `forward`: [content, style (N, 1, 512), trajectory]
        return self.denoiser(sample=x_t, timestep=t, encoder_hidden_states=[content, style[:, None, :], trajectory],
                             lengths=mask > 0.5)[0]


@contextlib.contextmanager
def export_patches(official: Official):
    """The tracing-only fixes of the module docstring; everything is restored on exit."""
    squeeze = torch.Tensor.squeeze

    def squeeze_traceable(self, *args, **kwargs):
        dim = args[0] if args else kwargs.get("dim")
        if isinstance(dim, int) and not isinstance(self.shape[dim], int):
            # A dynamic (symbolic) axis: torch squeezes it only at size 1, ONNX Squeeze fails
            # unless it is 1. The one case, the VAE decoder's `.squeeze(0)` over T frames
            # (mld_vae.py `decode`), is a no-op for every T > 1; at T = 1 the official decoder
            # drops the frame axis and fails itself.
            return self
        return squeeze(self, *args, **kwargs)

    def mask_passthrough(lengths, device, max_len=None):
        return lengths

    saved = [(official.mld_vae, "lengths_to_mask", official.mld_vae.lengths_to_mask),
             (official.mld_denoiser, "lengths_to_mask", official.mld_denoiser.lengths_to_mask),
             (torch.Tensor, "squeeze", squeeze)]
    validate = torch.distributions.Distribution._validate_args
    try:
        official.mld_vae.lengths_to_mask = mask_passthrough
        official.mld_denoiser.lengths_to_mask = mask_passthrough
        torch.Tensor.squeeze = squeeze_traceable
        # Normal's argument check is data-dependent control flow, which torch.export refuses.
        torch.distributions.Distribution.set_default_validate_args(False)
        yield
    finally:
        for owner, name, value in saved:
            setattr(owner, name, value)
        torch.distributions.Distribution.set_default_validate_args(validate)


def example_inputs(role: str, n: int = 2, t: int = 40) -> tuple:
    """Example inputs of one role, in the contract's input order. N and T above 1: torch.export
    specialises an axis whose example size is 0 or 1."""
    g = torch.Generator().manual_seed(0)

    def randn(*shape):
        return torch.randn(*shape, generator=g)

    mask = torch.ones(n, t)
    latent = randn(n, LATENT_TOKENS, LATENT_DIM)
    return {
        "vae_encoder": (randn(n, t, E.DIM), mask),
        "vae_decoder": (latent, mask),
        "style_encoder": (randn(n, t, E.DIM), mask),
        "denoiser": (latent, torch.full((n,), 500, dtype=torch.int64), randn(n, LATENT_TOKENS, LATENT_DIM),
                     randn(n, t, E.TRAJ_DIMS), mask, randn(n, E.STYLE_DIM)),
    }[role]


def wrappers(official: Official) -> dict:
    return {"vae_encoder": VaeEncoder(official.vae), "vae_decoder": VaeDecoder(official.vae),
            "style_encoder": StyleEncoder(official.motionclip_encoder), "denoiser": Denoiser(official.denoiser)}


# Longest T each role's positional tables allow: learned tables of 500 rows
# (position_encoding.py PositionEmbeddingLearned1D max_len=500) hold T + 14 query tokens in the
# VAE encoder, T in the VAE decoder, T + 1 global token in the trajectory encoder; MotionCLIP's
# sinusoidal table has 5000 rows for T + 2 tokens (transformer.py PositionalEncoding max_len=5000).
MAX_T = {"vae_encoder": E.MAX_FRAMES, "vae_decoder": 500, "denoiser": 500 - 1, "style_encoder": 5000 - 2}


def export(official: Official, out_dir: Path) -> None:
    """One ONNX file per role (opset 18, dynamic N and T), named as in `mcm_ldm.COMPONENTS`.

    torch.export (dynamo) rather than the TorchScript tracer: the tracer freezes the key length
    of nn.MultiheadAttention in MotionCLIP's encoder to the example's T."""
    # onnxscript's optimiser logs a warning for every Split it leaves unfolded (hundreds).
    optimiser_log = logging.getLogger("onnxscript")
    level = optimiser_log.level
    optimiser_log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            # N and T are shared by several inputs on purpose: the exporter says so once per input.
            warnings.filterwarnings("ignore", message="# The axis name")
            for role, module in wrappers(official).items():
                export_one(official, role, module, out_dir)
    finally:
        optimiser_log.setLevel(level)


def export_one(official: Official, role: str, module: torch.nn.Module, out_dir: Path) -> None:
    file, inputs, outputs = E.COMPONENTS[role]
    dims = {"N": torch.export.Dim("N", max=4096), "T": torch.export.Dim("T", max=MAX_T[role])}
    dynamic = {name: {i: dims[d] for i, d in enumerate(shape) if isinstance(d, str)} for name, shape in inputs}
    # The exporter prints its progress and optimiser notes to stdout: shown only on failure.
    log = io.StringIO()
    try:
        with export_patches(official), torch.no_grad(), contextlib.redirect_stdout(log):
            torch.onnx.export(module.eval(), example_inputs(role), str(out_dir / file),
                              input_names=[n for n, _ in inputs], output_names=[n for n, _ in outputs],
                              dynamic_shapes=dynamic, opset_version=E.OPSET, dynamo=True,
                              external_data=False, verbose=False)
    except Exception:
        sys.stdout.write(log.getvalue())
        raise
    strip_metadata(out_dir / file)


def strip_metadata(path: Path) -> None:
    """Drop the exporter's per-node notes (stack traces with this machine's absolute paths, FX
    node text; ~0.5 MB per file) and save deterministically, so the same checkpoints give the
    same bytes wherever they are exported."""
    import onnx

    model = onnx.load(str(path))
    graph = model.graph
    for item in [*graph.node, *graph.value_info, *graph.input, *graph.output, *graph.initializer]:
        del item.metadata_props[:]
    del model.metadata_props[:]
    E.C.save_model(model, path)


# --- the official inference, for --verify ----------------------------------------------------

def official_components(official: Official, role: str, feeds: dict) -> np.ndarray:
    """One role evaluated by the official modules exactly as mld.py calls them (lengths lists)."""
    f = {k: torch.from_numpy(v) for k, v in feeds.items()}
    lengths = [int(x) for x in f["mask"].sum(1)] if "mask" in f else None
    with torch.no_grad():
        if role == "vae_encoder":
            _, dist = official.vae.encode(f["features"], lengths)
            out = dist.loc.permute(1, 0, 2)
        elif role == "vae_decoder":
            out = official.vae.decode(f["latent"].permute(1, 0, 2), lengths)
        elif role == "style_encoder":
            x = f["features"].permute(0, 2, 1).unsqueeze(2)
            out = official.motionclip_encoder({"x": x, "y": torch.zeros(x.shape[0], dtype=torch.int64),
                                               "mask": official.lengths_to_mask(lengths, x.device)})["mu"]
        else:
            # The official denoiser takes one timestep for the whole batch (mld.py passes `t`).
            t = f["t"][0]
            out = official.denoiser(sample=f["x_t"], timestep=t,
                                    encoder_hidden_states=[f["content"], f["style"][:, None, :], f["trajectory"]],
                                    lengths=lengths)[0]
    return out.numpy()


def official_transfer(official: Official, mean: np.ndarray, std: np.ndarray, content: np.ndarray,
                      style: np.ndarray, x_t: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """MLD.forward and MLD._diffusion_reverse (mld/models/modeltype/mld.py) for one content/style
    pair at batch 1, as demo_transfer.py runs them, with x_T given and the VAE's posterior mean in
    place of its sample. Returns (normalised features (T, 263), joints (T, 22, 3))."""
    from diffusers import DDIMScheduler

    params = official.scheduler_config
    scheduler = DDIMScheduler(**params["params"])
    mean_t, std_t = torch.from_numpy(mean), torch.from_numpy(std)
    with torch.no_grad():
        motion = torch.from_numpy(style)[None].clone()
        motion[..., :3] = 0
        content_motion = (torch.from_numpy(content)[None] - mean_t) / std_t
        trans_motion = content_motion.clone()
        content_motion[..., :3] = 0
        lengths = [content_motion.shape[1]]
        _, dist = official.vae.encode(content_motion.float(), lengths)
        z = dist.loc
        motion_emb_content = torch.cat([z, z], dim=1).permute(1, 0, 2)
        motion_seq = motion.unsqueeze(-1).permute(0, 2, 3, 1)
        motion_emb = official.motionclip_encoder({
            "x": motion_seq.float(), "y": torch.zeros(1, dtype=torch.int64),
            "mask": official.lengths_to_mask([motion.shape[1]], motion_seq.device)})["mu"].unsqueeze(1)
        motion_emb = torch.cat([torch.zeros(motion_emb.shape), motion_emb], dim=0)
        trans_cond = trans_motion[..., :3]
        hidden = [motion_emb_content, motion_emb, torch.cat([trans_cond, trans_cond], dim=0)]

        latents = torch.from_numpy(x_t).reshape(1, LATENT_TOKENS, LATENT_DIM) * scheduler.init_noise_sigma
        scheduler.set_timesteps(params["num_inference_timesteps"])
        for t in scheduler.timesteps:
            noise_pred = official.denoiser(sample=torch.cat([latents] * 2), timestep=t,
                                           encoder_hidden_states=hidden, lengths=lengths * 2)[0]
            uncond, cond = noise_pred.chunk(2)
            noise_pred = uncond + scale * (cond - uncond)
            latents = scheduler.step(noise_pred, t, latents, eta=params["eta"]).prev_sample
        feats = official.vae.decode(latents.permute(1, 0, 2), lengths)
        # datamodule.feats2joints (mld/data/HumanML3D.py): denormalise, recover_from_ric(., 22)
        joints = official.recover_from_ric(feats * std_t + mean_t, E.JOINTS)
    return feats[0].numpy(), joints[0].numpy()
