"""Closed-form oracle for DDIM inversion followed by DDIM sampling, checked with plain numpy.

For data N(m, s^2) per channel the optimal denoiser is analytic, and the probability-flow ODE keeps
each level's standardised value z = (x_t - sqrt(a_t) m) / sqrt(a_t s^2 + 1 - a_t) unchanged. So
inverting clean data x under N(mc, sc^2) up to the top timestep T and sampling back under
N(ms, ss^2) has the closed form (a_T = alphas_cumprod[T]):

    x_T = sqrt(a_T) mc + sqrt(a_T sc^2 + 1 - a_T) (x - mc) / sc
    out = ms + ss (x_T - sqrt(a_T) ms) / sqrt(a_T ss^2 + 1 - a_T)

This script prints (1) the closed form against a fine RK4 solve of the ODE, which validates the
formula itself, and (2) the RMS error of a plain numpy DDIM (eta 0, scaled-linear schedule,
set_alpha_to_one true: both ends at alpha_bar 1) to the closed form at 50, 200 and 1000 steps, for
two timestep spacings and both places to evaluate the model during inversion. Numbers are in
models/tests/fixtures/schedulers/README.md. Needs only numpy:

    python models/diffusion-reference/gaussian_oracle.py
"""

import math

import numpy as np

TRAIN_STEPS = 1000
# Scaled-linear betas of Stable Diffusion / MLD / MCM-LDM (DESIGN.md): linspace of the square
# roots of 0.00085..0.012, squared (diffusers scheduling_ddim.py __init__).
BETAS = np.linspace(0.00085**0.5, 0.012**0.5, TRAIN_STEPS) ** 2
ALPHAS_CUMPROD = np.cumprod(1.0 - BETAS)

# Per-channel content (inversion) and style (sampling) Gaussians; s from 0.3 to 2 so that both
# sharp and broad channels are exercised.
M_CONTENT = np.array([0.5, -1.0, 2.0, 0.0])
S_CONTENT = np.array([0.5, 1.0, 1.5, 0.8])
M_STYLE = np.array([-0.5, 1.0, 0.0, 1.5])
S_STYLE = np.array([1.0, 0.6, 0.7, 2.0])
SAMPLES = 4000
# The RK4 check is slow (80000 evaluations); a few hundred samples suffice to validate a formula.
RK4_SAMPLES = 400
SEED = 0


def eps_hat(x, a, m, s):
    """Optimal epsilon for N(m, s^2) data at level a: sqrt(1-a) (x - sqrt(a) m) / (a s^2 + 1 - a).

    Equal to (x - sqrt(a) x0_hat) / sqrt(1 - a) with x0_hat = m + sqrt(a) s^2 (x - sqrt(a) m) /
    (a s^2 + 1 - a), written without the division so that it is finite (0) at a = 1.
    """
    return math.sqrt(1.0 - a) * (x - math.sqrt(a) * m) / (a * s * s + 1.0 - a)


def ddim_move(x, a_from, a_to, eps):
    """One deterministic DDIM update (Song et al. 2021, eq. 12 with sigma 0) between two levels."""
    x0 = (x - math.sqrt(1.0 - a_from) * eps) / math.sqrt(a_from)
    return math.sqrt(a_to) * x0 + math.sqrt(1.0 - a_to) * eps


def closed_form(x, a_top):
    x_top = math.sqrt(a_top) * M_CONTENT + np.sqrt(a_top * S_CONTENT**2 + 1.0 - a_top) * (
        x - M_CONTENT
    ) / S_CONTENT
    return M_STYLE + S_STYLE * (x_top - math.sqrt(a_top) * M_STYLE) / np.sqrt(
        a_top * S_STYLE**2 + 1.0 - a_top
    )


def timesteps(spacing, steps):
    """Ascending inference timesteps as diffusers' DDIM set_timesteps makes them (steps_offset 0)."""
    if spacing == "leading":
        return np.arange(steps) * (TRAIN_STEPS // steps)
    return np.round(np.arange(TRAIN_STEPS, 0, -TRAIN_STEPS / steps)).astype(np.int64)[::-1] - 1


def invert_then_sample(x, spacing, steps, model_at):
    """DDIM inversion under the content Gaussian, then DDIM sampling under the style Gaussian.

    Levels: alpha_bar 1 (the clean data), then alphas_cumprod at each timestep. Inversion from
    level a to level b evaluates the model at b ("target": diffusers' DDIMInverseScheduler with
    its pipelines, which call the model at t and step from t - ratio to t) or at a ("current").
    Sampling evaluates at the upper level, as DDIM does.
    """
    levels = [1.0] + [ALPHAS_CUMPROD[t] for t in timesteps(spacing, steps)]
    y = x.copy()
    for a, b in zip(levels[:-1], levels[1:]):
        at = b if model_at == "target" else a
        y = ddim_move(y, a, b, eps_hat(y, at, M_CONTENT, S_CONTENT))
    for a, b in zip(levels[:0:-1], levels[-2::-1]):
        y = ddim_move(y, a, b, eps_hat(y, a, M_STYLE, S_STYLE))
    return y, levels[-1]


def rk4_flow(x, a_top, substeps=20000):
    """The same map by RK4 on the probability-flow ODE in DDIM's coordinates.

    With xb = x / sqrt(a) and sigma = sqrt((1 - a) / a), the ODE is d xb / d sigma = eps_hat
    (Song et al. 2021, eq. 14); a = 1 / (1 + sigma^2).
    """

    def integrate(xb, s0, s1, m, s):
        h = (s1 - s0) / substeps

        def f(xb, sig):
            a = 1.0 / (1.0 + sig * sig)
            return eps_hat(xb * math.sqrt(a), a, m, s)

        sig = s0
        for _ in range(substeps):
            k1 = f(xb, sig)
            k2 = f(xb + 0.5 * h * k1, sig + 0.5 * h)
            k3 = f(xb + 0.5 * h * k2, sig + 0.5 * h)
            k4 = f(xb + h * k3, sig + h)
            xb = xb + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
            sig += h
        return xb

    sigma_top = math.sqrt((1.0 - a_top) / a_top)
    xb = integrate(x, 0.0, sigma_top, M_CONTENT, S_CONTENT)
    return integrate(xb, sigma_top, 0.0, M_STYLE, S_STYLE)


def rms(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)))


def main():
    rng = np.random.default_rng(SEED)
    x = M_CONTENT + S_CONTENT * rng.standard_normal((SAMPLES, M_CONTENT.size))
    a_top = ALPHAS_CUMPROD[TRAIN_STEPS - 1]
    naive = M_STYLE + (x - M_CONTENT) * S_STYLE / S_CONTENT
    print(f"alphas_cumprod[999] = {a_top:.6g}")
    few = x[:RK4_SAMPLES]
    print(f"closed form vs RK4 ODE solve (20000 substeps each way, {RK4_SAMPLES} samples): RMS "
          f"{rms(rk4_flow(few, a_top), closed_form(few, a_top)):.2e}")
    print(f"closed form vs the a_T = 0 shortcut ms + (x - mc) ss / sc: RMS "
          f"{rms(naive, closed_form(x, a_top)):.4f}")
    print("RMS error of numpy DDIM (invert then sample) to the closed form:")
    print(f"{'spacing':<9} {'model during inversion':<23} {'50':>9} {'200':>9} {'1000':>9}")
    for spacing in ("leading", "trailing"):
        for model_at in ("target", "current"):
            errors = []
            for steps in (50, 200, 1000):
                y, a_end = invert_then_sample(x, spacing, steps, model_at)
                errors.append(rms(y, closed_form(x, a_end)))
            print(f"{spacing:<9} {model_at:<23} " + " ".join(f"{e:9.6f}" for e in errors))


if __name__ == "__main__":
    main()
