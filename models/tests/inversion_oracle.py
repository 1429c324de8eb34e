"""Independent float64 numpy DDIM for models/tests/inversion_oracle.rs (not run in CI).

Inverts x under N(mc, sc^2) per channel with the analytic optimal epsilon (network evaluated
at the target timestep, as diffusers' DDIM inversion pipelines do), samples back under
N(ms, ss^2), and prints the RMS error to the closed-form affine result for 50, 200, 1000
steps (leading spacing, steps_offset 0, set_alpha_to_one). Run: python inversion_oracle.py
"""
import numpy as np

betas = np.linspace(0.00085**0.5, 0.012**0.5, 1000) ** 2
ab = np.cumprod(1 - betas)
CONTENT = [(0.5, 1.0), (-1.0, 0.5), (2.0, 1.5)]
STYLE = [(-0.3, 0.7), (1.2, 2.0), (0.0, 0.4)]
K = 41
z = np.linspace(-2, 2, K)
x0 = np.concatenate([m + s * z for m, s in CONTENT])
mc, sc = (np.repeat([p[i] for p in CONTENT], K) for i in (0, 1))
ms, ss = (np.repeat([p[i] for p in STYLE], K) for i in (0, 1))


def eps(x, a, m, s):
    return np.sqrt(1 - a) * (x - np.sqrt(a) * m) / (a * s * s + 1 - a)


for n in [50, 200, 1000]:
    r = 1000 // n
    ts = np.arange(0, n) * r
    x, a_prev = x0.copy(), 1.0
    for t in ts:
        e = eps(x, ab[t], mc, sc)
        x0_hat = (x - np.sqrt(1 - a_prev) * e) / np.sqrt(a_prev)
        x, a_prev = np.sqrt(ab[t]) * x0_hat + np.sqrt(1 - ab[t]) * e, ab[t]
    for t in ts[::-1]:
        a_next = ab[t - r] if t - r >= 0 else 1.0
        e = eps(x, ab[t], ms, ss)
        x0_hat = (x - np.sqrt(1 - ab[t]) * e) / np.sqrt(ab[t])
        x = np.sqrt(a_next) * x0_hat + np.sqrt(1 - a_next) * e
    top = ab[ts[-1]]
    x_top = np.sqrt(top) * mc + (x0 - mc) / sc * np.sqrt(top * sc * sc + 1 - top)
    want = ms + ss * (x_top - np.sqrt(top) * ms) / np.sqrt(top * ss * ss + 1 - top)
    print(n, np.sqrt(np.mean((x - want) ** 2)))
