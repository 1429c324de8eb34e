import sys, h5py, numpy as np
with h5py.File(sys.argv[1], 'r+') as f:
    f['motion'].attrs['fps'] = np.float32(1e-4)
print('ok')
