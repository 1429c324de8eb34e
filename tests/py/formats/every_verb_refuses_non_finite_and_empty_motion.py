import sys, numpy as np
j = np.zeros((10, 22, 3), np.float32); j[4, 5, 1] = np.nan
np.save(sys.argv[1], j)
j[4, 5, 1] = np.inf
np.save(sys.argv[2], j)
np.save(sys.argv[3], np.zeros((0, 22, 3), np.float32))
print("ok")
