import sys, numpy as np
a = np.load(sys.argv[1]); b = np.load(sys.argv[2])
assert a.dtype == np.float32 and a.shape == (80, 1921), (a.dtype, a.shape)
d = np.abs(a - b)
assert d.mean() <= 0.1, d.mean()
print(f"ok mean |d| {d.mean():.4f} dB")
