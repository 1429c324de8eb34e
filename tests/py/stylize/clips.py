import sys, numpy as np
f = np.load(sys.argv[1])
assert f.shape[1] == 263 and len(f) >= 230, f.shape
np.save(sys.argv[2], f[:150])
np.save(sys.argv[3], f[110:230])
print("ok")
