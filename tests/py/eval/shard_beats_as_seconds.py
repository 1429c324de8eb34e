# The music beats `choreod prep` stored with a shard's sequence (frame indices at the shard's
# root fps) written as seconds, one per line, for `choreod eval --beats`.
import sys, h5py
f = h5py.File(sys.argv[1], 'r')
fps = float(f.attrs['fps'])
b = f[sys.argv[2]]['beats'][()]
assert len(b) > 2, b
open(sys.argv[3], 'w').write(''.join(f'{float(x) / fps!r}\n' for x in b))
print(f"ok {len(b)} beats at {fps} fps")
