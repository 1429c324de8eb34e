import sys, h5py, numpy as np
np.save(sys.argv[3], h5py.File(sys.argv[1], 'r')[sys.argv[2]]['joints60'][()])
print("ok")
