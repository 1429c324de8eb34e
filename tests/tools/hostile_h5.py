#!/usr/bin/env python3
"""Motion files that crash Debian's libhdf5 1.10.8 (SIGSEGV, heap over-read), for the tests of
choreod's isolated HDF5 reader (issue 20, item 2). Both are what a hostile upload looks like:

  hostile_h5.py heap-flip SRC DST   SRC (a valid motion file choreod wrote) with one bit flipped:
                                    bit 4 of the third byte of the size of the first object in
                                    the global heap (the `format` attribute's string), so the
                                    string claims 1 MiB more than the heap holds.
  hostile_h5.py short-chunk DST     a motion file whose /motion/joints (720, 24, 3) float32 is
                                    chunked, unfiltered, with its only chunk (nominal 207,360
                                    bytes) stored as 10 bytes (h5py's write_direct_chunk).
  hostile_h5.py shard DST [BEAT...] a `choreod prep` shard (root format "choreod-prep-shard")
                                    of one AIST++ sequence, 120 frames of SMPL-24 joints
                                    (seeded noise about standing height): what an upload of a
                                    shard to eval looks like, for checking where it is read.
                                    With BEATs (integers, any value), the sequence's `beats`
                                    (int32) and the root `fps` (30) that times them, as prep
                                    writes them.

Global heap layout (HDF5 file format spec, "Global Heap"): "GCOL", version (1), reserved (3),
collection size (8); then objects: index (2), reference count (2), reserved (4), size (8), data.
"""
import sys

import h5py
import numpy as np


def heap_flip(src, dst):
    data = bytearray(open(src, "rb").read())
    gcol = data.find(b"GCOL")
    if gcol < 0:
        sys.exit(f"{src}: no global heap collection")
    size_at = gcol + 16 + 8
    data[size_at + 2] ^= 0x10
    open(dst, "wb").write(bytes(data))


def short_chunk(dst):
    frames, joints = 720, 24
    with h5py.File(dst, "w", libver="earliest") as f:
        text = h5py.string_dtype()
        f.attrs.create("format", "choreod-motion", dtype=text)
        f.attrs["format_version"] = np.int64(2)
        f.attrs.create("generator", "hostile", dtype=text)
        f.attrs.create("created_utc", "2026-01-01T00:00:00Z", dtype=text)
        m = f.create_group("motion")
        m.attrs["fps"] = np.float32(60)
        m.attrs.create("skeleton", "smpl24", dtype=text)
        m.attrs.create("joint_names", [f"j{i}" for i in range(joints)], dtype=text)
        m.attrs["parents"] = np.array([-1] + list(range(joints - 1)), dtype=np.int32)
        m.attrs.create("up_axis", "y", dtype=text)
        m.attrs.create("units", "m", dtype=text)
        shape = (frames, joints, 3)
        d = m.create_dataset("joints", shape=shape, maxshape=(None, joints, 3), chunks=shape, dtype="f4")
        d.id.write_direct_chunk((0, 0, 0), b"\0" * 10)


def shard(dst, beats):
    with h5py.File(dst, "w", libver="earliest") as f:
        text = h5py.string_dtype()
        f.attrs.create("format", "choreod-prep-shard", dtype=text)
        f.attrs["format_version"] = np.int64(1)
        f.attrs.create("dataset", "aistpp", dtype=text)
        g = f.create_group("gBR_sBM_cAll_d04_mBR0_ch01")
        joints = np.random.default_rng(0).standard_normal((120, 24, 3)) * 0.1 + [0, 1, 0]
        g.create_dataset("joints60", data=joints.astype("f4"))
        if beats:
            f.attrs["fps"] = np.float32(30)
            g.create_dataset("beats", data=np.array(beats, dtype="i4"))


if __name__ == "__main__":
    if sys.argv[1:2] == ["heap-flip"] and len(sys.argv) == 4:
        heap_flip(sys.argv[2], sys.argv[3])
    elif sys.argv[1:2] == ["short-chunk"] and len(sys.argv) == 3:
        short_chunk(sys.argv[2])
    elif sys.argv[1:2] == ["shard"] and len(sys.argv) >= 3:
        shard(sys.argv[2], [int(b) for b in sys.argv[3:]])
    else:
        sys.exit(__doc__)
