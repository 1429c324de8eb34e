#!/usr/bin/env python3
"""The library's source positions against an independent BVH reader: Blender's importer.

For one file of each dance-library rig, every 10th frame: the world positions choreod's reader
gives (`choreod convert X.bvh -o X.h5`, /motion/joints with joint names) against Blender's
(`import_anim.bvh` with no axis conversion, pose-bone heads), and the direction of every
parent-child bone between them. The library's SMPL-24 joints are those positions placed by name
(tests/tests/formats.rs convert_to_smpl24_places_every_dance_library_rig), so this checks what
the retarget starts from.

    .venv/bin/python models/packages/check_library_against_blender.py [--choreod target/release/choreod]

Local only (needs `blender` and ../shared); prints one line per file.
"""

from __future__ import annotations

import argparse
import gzip
import subprocess
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent.parent / "shared"
FILES = ["cmu-60-61-salsa/60_10_scaled", "cmu-85-breakdance/85_03", "cmu-05-modern/005_03", "cmu-55-dance/55_01"]
STEP = 10

BLENDER_SIDE = r'''
import builtins, struct, sys
import bpy
bvh, names_path, out_path, step = sys.argv[sys.argv.index("--") + 1:]
real_open = builtins.open
builtins.open = lambda f, mode="r", *a, **k: real_open(f, mode.replace("U", ""), *a, **k)  # Blender 3.4 'rU'
names = real_open(names_path).read().split()
frames = int(real_open(bvh).read().split("Frames:", 1)[1].split()[0])
before = set(bpy.data.objects)
bpy.ops.import_anim.bvh(filepath=bvh, global_scale=1.0, axis_forward="Y", axis_up="Z", frame_start=1,
                        use_fps_scale=False, update_scene_duration=True)
builtins.open = real_open
(arm,) = set(bpy.data.objects) - before
bones = [arm.pose.bones[n] for n in names]
with real_open(out_path, "wb") as out:
    for i in range(0, frames, int(step)):
        bpy.context.scene.frame_set(1 + i)
        out.write(struct.pack(f"<{3 * len(bones)}f", *(c for b in bones for c in arm.matrix_world @ b.head)))
'''


def main() -> None:
    import h5py

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--choreod", type=Path, default=HERE.parent.parent / "target" / "release" / "choreod")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        (tmp / "side.py").write_text(BLENDER_SIDE)
        for rel in FILES:
            bvh = tmp / (Path(rel).name + ".bvh")
            bvh.write_bytes(gzip.open(SHARED / "data" / "dance-mocap" / (rel + ".bvh.gz")).read())
            subprocess.run([str(a.choreod), "convert", str(bvh), "-o", str(tmp / "c.h5")], check=True,
                           capture_output=True)
            with h5py.File(tmp / "c.h5") as f:
                ours = f["motion/joints"][()][::STEP].astype(np.float64)
                names = [n if isinstance(n, str) else n.decode() for n in f["motion"].attrs["joint_names"]]
                parents = f["motion"].attrs["parents"]
            (tmp / "names").write_text(" ".join(names))
            subprocess.run(["blender", "--background", "--factory-startup", "--python", str(tmp / "side.py"), "--",
                            str(bvh), str(tmp / "names"), str(tmp / "b.f32"), str(STEP)], check=True,
                           capture_output=True)
            theirs = np.fromfile(tmp / "b.f32", "<f4").astype(np.float64).reshape(ours.shape)
            # Blender reads the file's units; choreod scales to metres: compare after the scale
            # that maps one onto the other (least squares).
            scale = float((ours * theirs).sum() / (theirs * theirs).sum())
            pos = np.linalg.norm(ours - scale * theirs, axis=-1)
            kids = [j for j, p in enumerate(parents) if p >= 0]
            bo = ours[:, kids] - ours[:, [parents[j] for j in kids]]
            bt = theirs[:, kids] - theirs[:, [parents[j] for j in kids]]
            lo, lt = np.linalg.norm(bo, axis=-1), np.linalg.norm(bt, axis=-1)
            real = (lo > 1e-4) & (lt * scale > 1e-4)  # zero-length bones have no direction
            cos = (bo * bt).sum(-1)[real] / (lo * lt)[real]
            angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
            print(f"{rel}: {ours.shape[0]} frames x {len(names)} joints; metres per file unit {scale:.6f}; "
                  f"position max {pos.max() * 1e6:.1f} um; bone direction max {angle.max():.5f} deg over "
                  f"{int(real.sum())} bones (min cosine {cos.min():.9f})")


if __name__ == "__main__":
    main()
