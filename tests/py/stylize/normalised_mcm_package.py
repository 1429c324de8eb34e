import sys, re, numpy as np
f = np.load(sys.argv[2])
toml = sys.argv[1] + "/choreod-model.toml"
text = open(toml).read()
arr = lambda v: "[" + ", ".join(repr(float(x)) for x in v) + "]"
text = re.sub(r"\nmean = \[[^\]]*\]", "\nmean = " + arr(f.mean(0)), text)
text = re.sub(r"\nstd = \[[^\]]*\]", "\nstd = " + arr(f.std(0) + 0.1), text)
assert text.count("mean = [") == 1 and "std = [1.0" not in text
open(toml, "w").write(text)
np.save(sys.argv[3], np.random.default_rng(3).standard_normal((7, 16)).astype(np.float32))
print("ok")
