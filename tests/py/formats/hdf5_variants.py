# A motion file made from `ok.h5` with `/motion/joints` (720, 24, 3) replaced by `make(g, j)`.
import sys, os, shutil, zlib, h5py, numpy as np
d = sys.argv[1]
def variant(name, make):
    dst = os.path.join(d, name)
    shutil.copy(os.path.join(d, "ok.h5"), dst)
    with h5py.File(dst, "r+") as f:
        j = f["motion/joints"][...]
        del f["motion/joints"]
        make(f["motion"], j)
def chunked(g, j, chunks=None, **kw):
    return g.create_dataset("joints", shape=j.shape, maxshape=(None, 24, 3), chunks=chunks or j.shape, dtype="f4", **kw)
# One unfiltered chunk stored as 10 bytes (nominal 207,360): libhdf5 1.10 read past it (SIGSEGV).
variant("short_chunk.h5", lambda g, j: chunked(g, j).id.write_direct_chunk((0, 0, 0), bytes(10)))
# One gzip chunk of 64 MB of zeros (nominal 207,360): libhdf5 inflates all of it.
variant("bomb.h5", lambda g, j: chunked(g, j, compression="gzip").id.write_direct_chunk((0, 0, 0), zlib.compress(bytes(64 << 20))))
# Chunks of (4,000,000, 24, 3) for 720 frames.
variant("huge_chunk.h5", lambda g, j: chunked(g, j, chunks=(4000000, 24, 3), compression="gzip").id.write_direct_chunk((0, 0, 0), zlib.compress(j.astype("<f4").tobytes())))
# A filter libhdf5 does not know (it searched its plugin directory for it).
def unknown_filter(g, j):
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk(j.shape)
    dcpl.set_filter(32123, h5py.h5z.FLAG_OPTIONAL, ())
    space = h5py.h5s.create_simple(j.shape, (h5py.h5s.UNLIMITED, 24, 3))
    x = h5py.h5d.create(g.id, b"joints", h5py.h5t.IEEE_F32LE, space, dcpl=dcpl)
    x.write_direct_chunk((0, 0, 0), j.astype("<f4").tobytes(), filter_mask=0)
variant("unknown_filter.h5", unknown_filter)
# What h5py users write: gzip + shuffle + Fletcher-32 in 64-frame chunks (the last one partial).
variant("gzip_ok.h5", lambda g, j: g.create_dataset("joints", data=j, maxshape=(None, 24, 3), chunks=(64, 24, 3), compression="gzip", shuffle=True, fletcher32=True))
print("ok")
