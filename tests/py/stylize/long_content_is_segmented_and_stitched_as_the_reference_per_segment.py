import sys, numpy as np
f = np.load(sys.argv[1])
long = np.concatenate([f, f])[:400]
np.save(sys.argv[2], long)
for k, start in enumerate((0, 102, 204)):
    np.save(sys.argv[3 + k], long[start:start + 196])
print("ok")
