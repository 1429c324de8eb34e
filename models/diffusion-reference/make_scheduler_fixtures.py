"""Golden scheduler trajectories from diffusers, for the Rust schedulers' tests.

Runs diffusers' own DDPMScheduler, DDIMScheduler, DPMSolverMultistepScheduler and
DDIMInverseScheduler on a small analytic denoiser (a Gaussian mixture per condition, whose exact
E[x0 | x_t] is known) and writes every step as JSON. The format and the denoiser's formulas are in
models/tests/fixtures/schedulers/README.md.

Needs torch and diffusers (a local reference environment only: never in setup, CI or at run
time). From the repository root:

    python models/diffusion-reference/make_scheduler_fixtures.py --out models/tests/fixtures/schedulers
"""

import argparse
import json
import math
import os
import platform
import tempfile
from pathlib import Path

import diffusers
import numpy as np
import torch
from diffusers import (
    DDIMInverseScheduler,
    DDIMScheduler,
    DDPMScheduler,
    DPMSolverMultistepScheduler,
)
from diffusers.utils.torch_utils import randn_tensor

FORMAT = "choreod-scheduler-golden"
FORMAT_VERSION = 1
TRAIN_STEPS = 1000
# (beta_start, beta_end) of DDPM/MoFusion and of Stable Diffusion/MLD/MCM-LDM.
SCHEDULES = {"linear": (1e-4, 0.02), "scaled_linear": (0.00085, 0.012)}
# Sample shape (rows N, frames T, channels D), as the Rust sampler's (N, T, D) windows.
SHAPE = (2, 3, 4)
SINGLE = {"kind": "single", "weight": 2.5}
# wc != ws so that swapping the two weights changes the result.
DOUBLE = {"kind": "double", "content": 1.5, "style": 3.0}
OFF = {"kind": "off"}


# ---------------------------------------------------------------- analytic denoiser


def make_mixtures(rng):
    """One diagonal Gaussian mixture over a whole (T, D) row per cond code.

    Codes as models/src/sampler.rs `Guidance`: 0 = null, 1 = content, 2 = content+style. Different
    K and parameters per code, so that swapping two conditions changes every step. Values are
    rounded to 2 decimals so the JSON holds them exactly.
    """
    weights = {0: [0.6, 0.4], 1: [0.5, 0.3, 0.2], 2: [0.35, 0.65]}
    mixtures = {}
    for code, w in weights.items():
        k = len(w)
        means = np.round(rng.uniform(-1.5, 1.5, size=(k,) + SHAPE[1:]), 2)
        stds = np.round(rng.uniform(0.1, 0.6, size=(k,) + SHAPE[1:]), 2)
        mixtures[code] = {"weights": w, "means": means, "stds": stds}
    return mixtures


def mixture_x0(mix, x_t, alpha_bar):
    """E[x0 | x_t] under the mixture at noise level alpha_bar, row by row (float64).

    x_t = sqrt(a) x0 + sqrt(1 - a) eps. Under mode k, x_t ~ N(sqrt(a) mu_k, a s_k^2 + 1 - a)
    (diagonal), and E[x0 | x_t, k] = mu_k + sqrt(a) s_k^2 / v_k (x_t - sqrt(a) mu_k).
    The mode posteriors r_k are a softmax over rows' log pi_k + log N(x_t; sqrt(a) mu_k, v_k).
    """
    a = float(alpha_bar)
    sa = math.sqrt(a)
    means = np.asarray(mix["means"])[None]  # (1, K, T, D)
    var0 = np.asarray(mix["stds"])[None] ** 2
    v = a * var0 + (1.0 - a)
    x = x_t[:, None]  # (N, 1, T, D)
    resid = x - sa * means
    log_n = -0.5 * (resid**2 / v + np.log(2.0 * math.pi * v)).sum(axis=(2, 3))
    logits = np.log(np.asarray(mix["weights"]))[None] + log_n  # (N, K)
    logits -= logits.max(axis=1, keepdims=True)
    r = np.exp(logits)
    r /= r.sum(axis=1, keepdims=True)
    x0_k = means + sa * var0 / v * resid  # (N, K, T, D)
    return (r[:, :, None, None] * x0_k).sum(axis=1)


def network_output(mixtures, x_t, alpha_bar, code, prediction):
    """What an ideal network trained on mixture `code` returns: epsilon or x0 ("sample")."""
    x0 = mixture_x0(mixtures[code], x_t, alpha_bar)
    if prediction == "sample":
        return x0
    return (x_t - math.sqrt(alpha_bar) * x0) / math.sqrt(1.0 - alpha_bar)


def guided_output(mixtures, x_t, alpha_bar, guidance, prediction):
    """Classifier-free guidance on the network output (models/src/sampler.rs `Guidance`)."""
    out = lambda code: network_output(mixtures, x_t, alpha_bar, code, prediction)  # noqa: E731
    if guidance["kind"] == "off":
        return out(1)
    if guidance["kind"] == "single":
        u, c = out(0), out(1)
        return u + guidance["weight"] * (c - u)
    u, c, cs = out(0), out(1), out(2)
    return u + guidance["content"] * (c - u) + guidance["style"] * (cs - c)


def sample_mixture(mix, rng):
    """Draw one (N, T, D) batch of data from the mixture (one mode per row)."""
    modes = rng.choice(len(mix["weights"]), size=SHAPE[0], p=mix["weights"])
    eps = rng.standard_normal(SHAPE)
    return np.asarray(mix["means"])[modes] + np.asarray(mix["stds"])[modes] * eps


# ---------------------------------------------------------------- schedulers


def alphas_cumprod_f64(schedule):
    """diffusers' beta formulas (scheduling_ddim.py __init__), evaluated in float64."""
    start, end = SCHEDULES[schedule]
    if schedule == "linear":
        betas = torch.linspace(start, end, TRAIN_STEPS, dtype=torch.float64)
    else:
        betas = torch.linspace(start**0.5, end**0.5, TRAIN_STEPS, dtype=torch.float64) ** 2
    return betas, torch.cumprod(1.0 - betas, dim=0)


def use_float64_schedule(sched, schedule):
    """Replace the float32 schedule diffusers builds in __init__ by the same formulas in float64.

    diffusers computes betas and their running product in float32 (scheduling_ddim.py,
    scheduling_ddpm.py, scheduling_dpmsolver_multistep.py, scheduling_ddim_inverse.py __init__);
    the Rust schedule is f64 (models/src/schedule.rs), so the fixture records the f64 math.
    Every attribute __init__ derives from alphas_cumprod is rebuilt here.
    """
    betas, cumprod = alphas_cumprod_f64(schedule)
    sched.betas = betas
    sched.alphas = 1.0 - betas
    sched.alphas_cumprod = cumprod
    one = torch.tensor(1.0, dtype=torch.float64)
    if isinstance(sched, DDIMScheduler):
        sched.final_alpha_cumprod = one if sched.config.set_alpha_to_one else cumprod[0]
    elif isinstance(sched, DDIMInverseScheduler):
        sched.initial_alpha_cumprod = one if sched.config.set_alpha_to_one else cumprod[0]
    elif isinstance(sched, DDPMScheduler):
        sched.one = one
    elif isinstance(sched, DPMSolverMultistepScheduler):
        sched.alpha_t = torch.sqrt(cumprod)
        sched.sigma_t = torch.sqrt(1.0 - cumprod)
        sched.lambda_t = torch.log(sched.alpha_t) - torch.log(sched.sigma_t)
        sched.sigmas = ((1.0 - cumprod) / cumprod) ** 0.5


def build_scheduler(case):
    start, end = SCHEDULES[case["schedule"]]
    common = dict(
        num_train_timesteps=TRAIN_STEPS,
        beta_start=start,
        beta_end=end,
        beta_schedule=case["schedule"],
        prediction_type=case["prediction"],
        timestep_spacing=case["spacing"],
        steps_offset=case["steps_offset"],
    )
    kind = case["sampler"]
    if kind == "ddpm":
        sched = DDPMScheduler(variance_type="fixed_small", clip_sample=False, **common)
    elif kind == "ddim":
        sched = DDIMScheduler(
            clip_sample=False, set_alpha_to_one=case["set_alpha_to_one"], **common
        )
    elif kind == "ddim_inverse":
        sched = DDIMInverseScheduler(
            clip_sample=False, set_alpha_to_one=case["set_alpha_to_one"], **common
        )
    else:
        sched = DPMSolverMultistepScheduler(
            algorithm_type="dpmsolver++",
            solver_order=2,
            solver_type="midpoint",
            lower_order_final=True,
            final_sigmas_type="zero",
            **common,
        )
    return sched


def tensor(a):
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))


def run_case(case, mixtures, float64_schedule=True):
    """Run one case through diffusers; returns (scheduler, timesteps, x_start, steps)."""
    sched = build_scheduler(case)
    if float64_schedule:
        use_float64_schedule(sched, case["schedule"])
    sched.set_timesteps(case["steps"])
    # The denoiser's noise level: the schedule the scheduler steps with (f64 or diffusers' f32).
    alpha_bar = sched.alphas_cumprod.to(torch.float64).numpy()
    rng = np.random.default_rng(case["seed"])
    if case["sampler"] == "ddim_inverse":
        x = sample_mixture(mixtures[1], rng)
    else:
        x = rng.standard_normal(SHAPE)
    x_start = x.copy()
    generator = torch.Generator().manual_seed(case["seed"])
    steps = []
    timesteps = sched.timesteps.tolist()
    for i, t in enumerate(timesteps):
        out = guided_output(mixtures, x, alpha_bar[t], case["guidance"], case["prediction"])
        record = {"t": t, "other_t": other_level(sched, case, timesteps, i), "model_output": out.tolist()}
        if case["sampler"] == "ddpm":
            state = generator.get_state()
            x_prev = sched.step(tensor(out), t, tensor(x), generator=generator).prev_sample
            record["noise"] = ddpm_noise_drawn(sched, t, state, out, x)
        elif case["sampler"] == "ddim":
            eta = case["eta"]
            noise = rng.standard_normal(SHAPE) if eta > 0 else None
            x_prev = sched.step(
                tensor(out),
                t,
                tensor(x),
                eta=eta,
                variance_noise=None if noise is None else tensor(noise),
            ).prev_sample
            record["noise"] = None if noise is None else noise.tolist()
        else:
            x_prev = sched.step(tensor(out), t, tensor(x)).prev_sample
        x = x_prev.to(torch.float64).numpy()
        record["x_prev"] = x.tolist()
        steps.append(record)
    return sched, sched.timesteps.tolist(), x_start, steps


def other_level(sched, case, timesteps, i):
    """The second noise level of step i, as diffusers picks it (-1: the final/initial alpha).

    DDIM: t - train_steps // steps even when the spacing is trailing or linspace
    (scheduling_ddim.py step); DDPM: the next listed timestep (previous_timestep);
    DPM-Solver++: the next listed timestep, -1 = sigma 0; inversion: the level the sample comes
    from, min(t - train_steps // steps, train_steps - 1) (scheduling_ddim_inverse.py step).
    """
    t = timesteps[i]
    ratio = TRAIN_STEPS // case["steps"]
    if case["sampler"] == "ddim":
        return t - ratio
    if case["sampler"] == "ddim_inverse":
        return min(t - ratio, TRAIN_STEPS - 1)
    if case["sampler"] == "ddpm":
        return int(sched.previous_timestep(t))
    return timesteps[i + 1] if i + 1 < len(timesteps) else -1


def ddpm_noise_drawn(sched, t, state, out, x):
    """The noise DDPMScheduler.step drew from `generator` at timestep t (None when t == 0).

    step draws once with randn_tensor(model_output.shape, generator, dtype=model_output.dtype)
    (scheduling_ddpm.py step). Replaying that call from the saved generator state gives the same
    tensor; checked by stepping again from another state: the outputs must differ by exactly
    sqrt(variance) * (noise difference).
    """
    if t == 0:
        return None
    replay = torch.Generator().set_state(state)
    noise = randn_tensor(tuple(out.shape), generator=replay, dtype=torch.float64)
    other = torch.Generator().manual_seed(987654321)
    other_state = other.get_state()
    a = sched.step(tensor(out), t, tensor(x), generator=torch.Generator().set_state(state))
    b = sched.step(tensor(out), t, tensor(x), generator=other)
    other_noise = randn_tensor(
        tuple(out.shape), generator=torch.Generator().set_state(other_state), dtype=torch.float64
    )
    std = sched._get_variance(t) ** 0.5
    gap = (a.prev_sample - b.prev_sample) - std * (noise - other_noise)
    assert float(gap.abs().max()) < 1e-12, "DDPM noise replay does not match diffusers' draw"
    return noise.numpy().tolist()


# ---------------------------------------------------------------- cases


def sampling_cases():
    cases = []
    seed = 100

    def add(**case):
        nonlocal seed
        seed += 1
        case.setdefault("prediction", "epsilon")
        case.setdefault("eta", 0.0)
        case.setdefault("set_alpha_to_one", False)
        case["seed"] = seed
        cases.append(case)

    # DDIM: every combination the issue names, 10 steps.
    for schedule in SCHEDULES:
        guidance = SINGLE if schedule == "linear" else DOUBLE
        for spacing in ("leading", "trailing", "linspace"):
            for eta in (0.0, 0.5):
                for a1 in (False, True):
                    add(
                        sampler="ddim",
                        schedule=schedule,
                        spacing=spacing,
                        steps_offset=1,
                        eta=eta,
                        set_alpha_to_one=a1,
                        guidance=guidance,
                        steps=10,
                    )
    add(sampler="ddim", schedule="scaled_linear", spacing="leading", steps_offset=1,
        guidance=SINGLE, prediction="sample", steps=10)
    add(sampler="ddim", schedule="linear", spacing="leading", steps_offset=0,
        guidance=OFF, steps=25)
    add(sampler="ddim", schedule="scaled_linear", spacing="trailing", steps_offset=1, eta=0.5,
        guidance=DOUBLE, steps=25)
    # DDPM (fixed_small).
    add(sampler="ddpm", schedule="linear", spacing="leading", steps_offset=1,
        guidance=SINGLE, steps=10)
    add(sampler="ddpm", schedule="scaled_linear", spacing="leading", steps_offset=1,
        guidance=DOUBLE, steps=10)
    add(sampler="ddpm", schedule="linear", spacing="leading", steps_offset=0,
        guidance=DOUBLE, steps=25)
    add(sampler="ddpm", schedule="scaled_linear", spacing="trailing", steps_offset=0,
        guidance=SINGLE, prediction="sample", steps=10)
    # DPM-Solver++ (2M); 10 steps (< 15: lower_order_final matters) and 25.
    for schedule in SCHEDULES:
        for steps, guidance in ((10, SINGLE), (25, DOUBLE)):
            add(sampler="dpmsolver++", schedule=schedule, spacing="linspace", steps_offset=0,
                guidance=guidance, steps=steps)
    add(sampler="dpmsolver++", schedule="scaled_linear", spacing="leading", steps_offset=1,
        guidance=SINGLE, steps=10)
    add(sampler="dpmsolver++", schedule="linear", spacing="linspace", steps_offset=0,
        guidance=DOUBLE, prediction="sample", steps=10)
    # DDIM inversion under the content condition alone (cond 1, no guidance), data -> top level.
    for schedule in SCHEDULES:
        add(sampler="ddim_inverse", schedule=schedule, spacing="leading", steps_offset=1,
            set_alpha_to_one=False, guidance=OFF, steps=10)
        add(sampler="ddim_inverse", schedule=schedule, spacing="trailing", steps_offset=0,
            set_alpha_to_one=True, guidance=OFF, steps=25)
    return cases


def case_name(case):
    parts = [case["sampler"].replace("+", "p"), case["schedule"], case["spacing"],
             f"off{case['steps_offset']}"]
    if case["sampler"] in ("ddim", "ddim_inverse"):
        parts.append("a1" if case["set_alpha_to_one"] else "a0")
    if case["sampler"] == "ddim":
        parts.append(f"eta{case['eta']:g}".replace(".", "p"))
    parts += [case["guidance"]["kind"], "eps" if case["prediction"] == "epsilon" else "x0",
              f"{case['steps']}steps"]
    return "_".join(parts)


def precision_note(sampler):
    if sampler == "dpmsolver++":
        return ("float32: diffusers stores the DPM-Solver sigmas as float32 (set_timesteps) and "
                "casts the sample to float32 in step (scheduling_dpmsolver_multistep.py); "
                "schedule built in float64, model outputs float64")
    return "float64: schedule rebuilt in float64, every tensor float64"


def config_dict(sched):
    """The scheduler's full config; non-finite floats (lambda_min_clipped = -inf) as strings,
    since JSON has no infinity."""
    def plain(v):
        return str(v) if isinstance(v, float) and not math.isfinite(v) else v

    return {k: plain(v) for k, v in dict(sched.config).items() if not k.startswith("_")}


# ---------------------------------------------------------------- single-call fixtures


def add_noise_fixture(rng):
    """DDPMScheduler.add_noise per schedule: one timestep per row."""
    shape = (4,) + SHAPE[1:]
    x0 = rng.standard_normal(shape)
    noise = rng.standard_normal(shape)
    timesteps = [0, 1, 500, 999]
    out = {}
    for schedule in SCHEDULES:
        sched = build_scheduler(dict(sampler="ddpm", schedule=schedule, prediction="epsilon",
                                     spacing="leading", steps_offset=0))
        use_float64_schedule(sched, schedule)
        noisy = sched.add_noise(tensor(x0), tensor(noise), torch.tensor(timesteps))
        out[schedule] = noisy.numpy().tolist()
    return {"timesteps": timesteps, "x0": x0.tolist(), "noise": noise.tolist(), "noisy": out}


def inverse_step_fixture(rng):
    """DDIMInverseScheduler.step alone, for given x and eps, at its first, a middle and last t."""
    cases = []
    for schedule in SCHEDULES:
        for a1, spacing, offset in ((False, "leading", 1), (True, "trailing", 0)):
            sched = build_scheduler(dict(sampler="ddim_inverse", schedule=schedule,
                                         prediction="epsilon", spacing=spacing,
                                         steps_offset=offset, set_alpha_to_one=a1))
            use_float64_schedule(sched, schedule)
            sched.set_timesteps(10)
            ts = sched.timesteps.tolist()
            for t in (ts[0], ts[4], ts[-1]):
                x = rng.standard_normal(SHAPE)
                eps = rng.standard_normal(SHAPE)
                x_next = sched.step(tensor(eps), t, tensor(x)).prev_sample
                cases.append({
                    "schedule": schedule,
                    "scheduler": {"class": "DDIMInverseScheduler", "config": config_dict(sched)},
                    "num_inference_steps": 10,
                    "timesteps": ts,
                    "t": t,
                    "from_t": min(t - TRAIN_STEPS // 10, TRAIN_STEPS - 1),
                    "x": x.tolist(),
                    "model_output": eps.tolist(),
                    "x_next": x_next.numpy().tolist(),
                })
    return cases


# ---------------------------------------------------------------- output


def versions():
    return {
        "diffusers": diffusers.__version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "script": "models/diffusion-reference/make_scheduler_fixtures.py",
    }


def write_json(path, obj):
    """Temp file + fsync + rename + fsync dir: a failed run leaves no half-written fixture."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(obj, f, separators=(",", ":"), allow_nan=False)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="fixture directory")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    mixtures = make_mixtures(np.random.default_rng(20261122))
    write_json(args.out / "denoiser.json", {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "shape": list(SHAPE),
        "mixtures": {
            str(code): {"weights": m["weights"], "means": m["means"].tolist(),
                        "stds": m["stds"].tolist()}
            for code, m in mixtures.items()
        },
    })

    index = []
    for case in sampling_cases():
        name = case_name(case)
        sched, timesteps, x_start, steps = run_case(case, mixtures)
        _, _, _, stock_steps = run_case(case, mixtures, float64_schedule=False)
        stock_gap = float(np.max(np.abs(np.asarray(stock_steps[-1]["x_prev"])
                                        - np.asarray(steps[-1]["x_prev"]))))
        cls = type(sched).__name__
        fixture = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "name": name,
            "generator": versions(),
            "precision": precision_note(case["sampler"]),
            "sampler": case["sampler"],
            "scheduler": {"class": cls, "config": config_dict(sched),
                          "step_kwargs": {"eta": case["eta"]} if case["sampler"] == "ddim" else {}},
            "schedule": case["schedule"],
            "num_inference_steps": case["steps"],
            "prediction_type": case["prediction"],
            "guidance": case["guidance"],
            "denoiser": "denoiser.json",
            "seed": case["seed"],
            "shape": list(SHAPE),
            "timesteps": timesteps,
            "x_start": x_start.tolist(),
            "steps": steps,
            "final_gap_to_float32_schedule": stock_gap,
        }
        write_json(args.out / f"{name}.json", fixture)
        index.append({"name": name, "file": f"{name}.json", "sampler": case["sampler"],
                      "steps": case["steps"]})
        print(f"{name}: {len(steps)} steps, |final - float32-schedule final|max = {stock_gap:.3g}")

    rng = np.random.default_rng(7)
    write_json(args.out / "add_noise.json", {
        "format": FORMAT, "format_version": FORMAT_VERSION, "generator": versions(),
        "scheduler": "DDPMScheduler.add_noise", **add_noise_fixture(rng),
    })
    write_json(args.out / "inverse_step.json", {
        "format": FORMAT, "format_version": FORMAT_VERSION, "generator": versions(),
        "cases": inverse_step_fixture(rng),
    })
    write_json(args.out / "index.json", {
        "format": FORMAT, "format_version": FORMAT_VERSION, "generator": versions(),
        "cases": index,
    })


if __name__ == "__main__":
    main()
