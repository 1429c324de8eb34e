"""What Blender makes of choreod's glTF files: run as
`blender -b --factory-startup --python tests/py/blender_gltf.py -- JOBS.json OUT.json`.

JOBS.json is a list of {"file", "fps", "frames": [motion frame indices], "bones": [names]}; for
each file, in one Blender process, this imports it (Blender's own glTF importer, the scene's
frame rate set to the motion's first, as glTF stores seconds) and writes to OUT.json a list of
{"file", "armatures", "bones", "frame_range", "fps", "heads": {frame: [[x, y, z] per bone]},
"meshes": [{"name", "groups": {group: vertices}, "armature_modifier"}]}. Heads are world
positions in glTF's frame (y up: Blender's (x, y, z) is glTF's (x, -z, y) turned back), metres;
motion frame f is evaluated at the scene frame of time f / fps.
"""
import json
import sys

import bpy
import numpy

# Blender 3.4's glTF importer (Debian 12's) still uses `np.bool`, which numpy 1.24 (Debian 12's)
# removed; it meant the builtin.
if not hasattr(numpy, "bool"):
    numpy.bool = bool

jobs_path, out_path = sys.argv[sys.argv.index("--") + 1:]
with open(jobs_path) as f:
    jobs = json.load(f)

results = []
for job in jobs:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = round(job["fps"])
    scene.render.fps_base = round(job["fps"]) / job["fps"]
    bpy.ops.import_scene.gltf(filepath=job["file"])
    armatures = [o for o in scene.objects if o.type == "ARMATURE"]
    result = {"file": job["file"], "armatures": len(armatures), "meshes": [], "heads": {}}
    if armatures:
        arm = armatures[0]
        result["bones"] = [b.name for b in arm.data.bones]
        action = arm.animation_data.action if arm.animation_data else None
        result["frame_range"] = list(action.frame_range) if action else None
        result["fps"] = scene.render.fps / scene.render.fps_base
        start = action.frame_range[0] if action else 0.0
        for frame in job["frames"]:
            whole = int(start + frame)
            scene.frame_set(whole, subframe=start + frame - whole)
            heads = []
            for name in job["bones"]:
                p = arm.matrix_world @ arm.pose.bones[name].head
                heads.append([p.x, p.z, -p.y])
            result["heads"][str(frame)] = heads
    for o in scene.objects:
        if o.type != "MESH":
            continue
        counts = {g.name: 0 for g in o.vertex_groups}
        names = {g.index: g.name for g in o.vertex_groups}
        for v in o.data.vertices:
            for g in v.groups:
                if g.weight > 0:
                    counts[names[g.group]] += 1
        result["meshes"].append({
            "name": o.name,
            "groups": counts,
            "armature_modifier": any(m.type == "ARMATURE" and m.object is not None
                                     for m in o.modifiers),
        })
    results.append(result)

with open(out_path, "w") as f:
    json.dump(results, f)
