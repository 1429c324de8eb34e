import sys, numpy as np
c = np.load(sys.argv[1])
np.save(sys.argv[2], c[:30])
c[5, 100] = np.nan
np.save(sys.argv[3], c)
print("ok")
