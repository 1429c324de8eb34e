import sys, numpy as np
j = np.load(sys.argv[1])
far = j.copy(); far[..., 0] += 3.0e7
np.save(sys.argv[2], far)
huge = j.copy(); huge[7, 3, 2] = 1.0e30
np.save(sys.argv[3], huge)
print("ok")
