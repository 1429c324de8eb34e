"""The torch half of lodge_verify_loop.py: LODGE's official inference loop, run from the clone.

The loop's own code runs, not a copy: the per-song body of `infer_lodge.py`'s `test`
(198-289), `Global_Module.render_sample_ori` (141-171), `Local_Module.render_sample` (158-299)
and `swap_left_right`, and `load_modata` are compiled from the clone's files (their modules import
training-only packages: torchmetrics, Lightning, rendering), the diffusion module is imported.
Three things are changed, at run time:
- `torch.randn` answers with the noise file's draws in the official order (checked by shape);
  `torch.randn_like`, the samplers' per-step noise, answers zeros: eta 0 multiplies it by 0;
- both samplers (diffusion.py:262-294 `ddim_sample`, 491-545 `inpaint_soft_ddim`) fix eta = 1
  in a local: they are recompiled from the clone's source with that literal set to 0;
- the samplers' results (the final normalised windows) are kept as they are returned.
"""

from __future__ import annotations

import ast
import contextlib
import functools
import importlib
import inspect
import os
import pickle
import subprocess
import sys
import tempfile
import textwrap
import types
from pathlib import Path

import numpy as np
import torch

import lodge as E
import lodge_torch as T

ETA_LITERAL = "sampling_timesteps, eta = shape[0], self.betas.device, self.n_timestep, 50, 1"


def _source_of(path: Path, name: str, cls: str | None = None) -> str:
    """The source of a module-level function or a method (with its decorators)."""
    text = path.read_text()
    tree = ast.parse(text)
    scope = tree.body
    if cls is not None:
        scope = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == cls).body
    node = next((n for n in scope if isinstance(n, ast.FunctionDef) and n.name == name), None)
    if node is None:
        raise E.ExportError(f"{path}: no {cls + '.' if cls else ''}{name}: a different LODGE than the one "
                            f"this check was written for")
    first = min([node.lineno] + [d.lineno for d in node.decorator_list])
    return textwrap.dedent("\n".join(text.splitlines()[first - 1:node.end_lineno]))


def _compile(source: str, filename: str, namespace: dict, name: str):
    exec(compile(source, filename, "exec"), namespace)  # noqa: S102  (the user's clone)
    return namespace[name]


def _song_body(path: Path) -> ast.Module:
    """`test`'s loop over the music folder (infer_lodge.py:197-289), as one statement."""
    tree = ast.parse(path.read_text())
    test = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "test")
    loops = [n for n in test.body if isinstance(n, ast.For) and "listdir" in ast.unparse(n.iter)]
    if len(loops) != 1:
        raise E.ExportError(f"{path}: test() has not the one loop over the music folder this check runs")
    return ast.Module(body=loops, type_ignores=[])


class Draws:
    """`torch.randn` answering with the file's draws in order."""

    def __init__(self, draws: list[np.ndarray]):
        self.draws = list(draws)
        self.used = 0

    def randn(self, *size, **kwargs):
        shape = tuple(size[0]) if len(size) == 1 and not isinstance(size[0], int) else tuple(size)
        if self.used == len(self.draws):
            raise E.ExportError(f"the official loop draws more than the file holds (torch.randn{shape})")
        want = self.draws[self.used]
        if tuple(want.shape) != shape:
            raise E.ExportError(f"official draw {self.used}: torch.randn{shape}, the file's is {want.shape}")
        self.used += 1
        return torch.from_numpy(np.array(want, dtype=np.float32)).to(kwargs.get("device") or "cpu")


@contextlib.contextmanager
def _patched_randn(draws: Draws):
    randn, randn_like = torch.randn, torch.randn_like
    torch.randn, torch.randn_like = draws.randn, torch.zeros_like
    try:
        yield
    finally:
        torch.randn, torch.randn_like = randn, randn_like


def _stub(name: str, **attrs) -> None:
    if name not in sys.modules:
        mod = types.ModuleType(name)
        mod.__dict__.update(attrs)
        sys.modules[name] = mod


class _ConstraintTaken(Exception):
    """Stops the official loop once the Local sampler has been handed its in-painting."""


def _diffusion(module, cfg, net, normalizer, horizon: int, kept: dict, key: str,
               given_x0: np.ndarray | None = None):
    """GaussianDiffusion as the configs build it (coarse_finedance_fea139.yaml:78-89,
    finedance_fea139_finetune_v2.yaml:73-84), its samplers at eta 0 and their results kept.
    With `given_x0` (the constraint check) the Global sampler returns those windows instead of
    sampling, and the Local sampler keeps its in-painting and stops the loop."""
    d = module.GaussianDiffusion(cfg, net, normalizer, horizon=horizon, repr_dim=E.NFEATS, smplx_model=None,
                                 n_timestep=E.TRAIN_STEPS, schedule="cosine", predict_epsilon=False,
                                 loss_type="l2", use_p2=False, cond_drop_prob=0.25, guidance_weight=E.GUIDANCE)
    for name in ("ddim_sample", "inpaint_soft_ddim"):
        source = textwrap.dedent(inspect.getsource(getattr(module.GaussianDiffusion, name)))
        if source.count(ETA_LITERAL) != 1:
            raise E.ExportError(f"diffusion.py {name}: its eta is not where this check sets it")
        fn = _compile(source.replace(ETA_LITERAL, ETA_LITERAL[:-1] + "0"), module.__file__, dict(module.__dict__), name)
        bound = types.MethodType(fn, d)

        def keep(*a, _bound=bound, **k):
            if key == "local":
                # The Local in-painting as the sampler receives it (diffusion.py:518-519).
                kept["local_constraint"] = {part: k["constraint"][part].detach().cpu().numpy().copy()
                                            for part in ("value", "mask")}
                if given_x0 is not None:
                    raise _ConstraintTaken
            elif given_x0 is not None:
                if tuple(a[0]) != given_x0.shape:
                    raise E.ExportError(f"the official Global sampler asks for {tuple(a[0])}, "
                                        f"choreod's windows are {given_x0.shape}")
                return torch.from_numpy(given_x0.astype(np.float32))
            out = _bound(*a, **k)
            kept[key] = out.detach().cpu().numpy().copy()
            return out
        setattr(d, name, keep)
    return d


@functools.cache
def _loaded_from(repo: Path, global_ckpt: Path, local_ckpt: Path, heads: int, allow_pickle: bool):
    official = T.Official(repo, allow_pickle=allow_pickle, need_pytorch3d=True)
    official.load(global_ckpt, local_ckpt, heads)
    return official


def _loaded(args):
    """The official networks, loaded once per process (the constraint check runs the loop twice)."""
    return _loaded_from(args.repo, args.global_ckpt, args.local_ckpt, args.heads, args.allow_pickle)


def run_official(args, features: np.ndarray, draws: list[np.ndarray],
                 global_x0: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The official loop's results; with `global_x0` (G, 104, 139) only the Local in-painting the
    official code builds from those Global windows (`constraint_value`, `constraint_mask`)."""
    repo = args.repo
    official = _loaded(args)
    # diffusion.py imports these for progress bars, parallel rendering and the 263-dim
    # representation only (motion_process.py no longer imports under numpy 2: np.float).
    _stub("tqdm", tqdm=lambda it, **_: it)
    _stub("p_tqdm", p_map=None)
    _stub("dld.data.render_joints.utils.motion_process", recover_from_ric=None)
    sys.path.insert(0, str(repo.resolve()))
    diffusion = importlib.import_module("dld.models.architectures.diffusion")
    preprocess = importlib.import_module("dld.data.utils.preprocess")
    smplfk = official.smplfk

    normalizer_path = args.normalizer or repo / E.NORMALIZER_PATH
    E.check_pickle_globals(normalizer_path)
    with torch.serialization.safe_globals([preprocess.Normalizer, preprocess.MinMaxScaler]):
        normalizer = torch.load(normalizer_path, map_location="cpu", weights_only=True)

    # The configs' values the loop reads (infer_lodge.py:311-315; --soft 1 as LODGE's README runs it).
    ns = types.SimpleNamespace
    cfg = ns(length1=E.GLOBAL_MUSIC_FRAMES, length2=E.LOCAL_FRAMES, soft=1.0, Norm=True,
             FINEDANCE=ns(nfeats=E.NFEATS, full_seq_len=E.GLOBAL_MUSIC_FRAMES),
             DEMO=ns(use_cached_features=True, RENDER=False))
    kept: dict[str, np.ndarray] = {}
    g_diff = _diffusion(diffusion, cfg, official.nets["global"], normalizer, E.GLOBAL_MUSIC_FRAMES, kept, "global",
                        global_x0)
    l_diff = _diffusion(diffusion, cfg, official.nets["local"], normalizer, E.LOCAL_FRAMES, kept, "local",
                        global_x0)

    rot = {"torch": torch, "np": np, "ax_from_6v": smplfk.ax_from_6v, "ax_to_6v": smplfk.ax_to_6v}
    modeltype = repo / "dld/models/modeltype"
    local_ns = dict(rot)
    local_ns["swap_left_right"] = _compile(_source_of(modeltype / "Local_Module.py", "swap_left_right"),
                                           "Local_Module.py", local_ns, "swap_left_right")
    render_local = _compile(_source_of(modeltype / "Local_Module.py", "render_sample", "Local_Module"),
                            "Local_Module.py", local_ns, "render_sample")
    render_global = _compile(_source_of(modeltype / "Global_Module.py", "render_sample_ori", "Global_Module"),
                             "Global_Module.py", dict(rot), "render_sample_ori")
    fine = ns(cfg=cfg, nfeats=E.NFEATS, normalizer=normalizer, diffusion=l_diff)
    coarse = ns(cfg=cfg, nfeats=E.NFEATS, normalizer=normalizer, diffusion=g_diff)
    fine.render_sample = types.MethodType(render_local, fine)
    coarse.render_sample_ori = types.MethodType(render_global, coarse)

    infer = repo / "infer_lodge.py"
    with tempfile.TemporaryDirectory(prefix="lodge-official-") as tmp:
        music_dir, out_dir = Path(tmp) / "music", Path(tmp) / "out"
        music_dir.mkdir()
        out_dir.mkdir()
        np.save(music_dir / "001.npy", features)
        song = dict(rot, os=os, pickle=pickle, cfg=cfg, music_dir=str(music_dir), test_list=["001"],
                    count=1, length_co=cfg.length1, length_fi=cfg.length2, device="cpu",
                    output_dir=str(out_dir), model_coarse=coarse, model_fine=fine,
                    setmode="inpaint_soft_ddim", music2genre_={"001": "verify"},
                    Genres_fd={"verify": args.genre}, extract_music35=None)
        song["load_modata"] = _compile(_source_of(infer, "load_modata"), str(infer), song, "load_modata")
        source = compile(_song_body(infer), str(infer), "exec")
        draw = Draws(draws)
        log_name = "official.log" if global_x0 is None else "official-constraint.log"
        try:
            with open(args.work / log_name, "w") as log, contextlib.redirect_stdout(log), \
                    _patched_randn(draw), torch.no_grad():
                exec(source, song)  # noqa: S102  (the user's clone)
        except _ConstraintTaken:
            taken = kept["local_constraint"]
            return {"constraint_value": taken["value"], "constraint_mask": taken["mask"]}
        if global_x0 is not None:
            raise E.ExportError("the official loop never called its Local sampler")
        if draw.used != len(draw.draws):
            raise E.ExportError(f"the official loop drew {draw.used} of the file's {len(draw.draws)} draws")
        n_local = len(kept["local"])
        # concat_res.py:73-97: the saved Local windows in order (the file names carry the batch index).
        dance = np.concatenate([np.load(out_dir / f"dod_{i}_{name}.npy")
                                for i, name in enumerate(_local_names(song, n_local))])
    skeleton = smplfk.SMPLX_Skeleton(Jpath=str(E.check_repo(repo)), batch=len(dance))
    with torch.no_grad():
        joints = smplfk.do_smplxfk(torch.from_numpy(dance), skeleton).numpy()
    return {"global_x0": kept["global"], "local_x0": kept["local"], "features": dance,
            "joints": joints[:, :22], "constraint_value": kept["local_constraint"]["value"],
            "constraint_mask": kept["local_constraint"]["mask"]}


def _local_names(song: dict, n: int) -> list[str]:
    names = song["all_localfilename_cat"]
    if len(names) != n:
        raise E.ExportError(f"the official loop named {len(names)} Local windows for {n} sampled")
    return names


def run_choreod(args) -> dict[str, np.ndarray]:
    import h5py

    out, windows = args.work / "choreod.h5", args.work / "choreod-windows.npz"
    cmd = [args.choreod, "dance", "--features", str(args.features), "--model", str(args.package),
           "--init-noise", str(args.work / "noise.npz"), "--sampler", "ddim", "--eta", "0",
           "--lodge-compat", "official", "--genre", str(args.genre), "--save-windows", str(windows),
           "-o", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    (args.work / "choreod.log").write_text(done.stderr)
    if done.returncode != 0:
        raise E.ExportError(f"choreod dance failed ({done.returncode}): {done.stderr.strip()[-500:]}")
    w = np.load(windows)
    missing = {"global_windows", "local_windows", "local_constraint_value", "local_constraint_mask"} - set(w.files)
    if missing:
        raise E.ExportError(f"{windows} lacks {sorted(missing)}: a choreod older than this check wrote it")
    with h5py.File(out, "r") as f:
        features = f["/motion/features"][()]
        joints = f["/motion/joints"][()]
    return {"global_x0": w["global_windows"], "local_x0": w["local_windows"], "features": features,
            "joints": joints[:, :22], "constraint_value": w["local_constraint_value"],
            "constraint_mask": w["local_constraint_mask"]}
