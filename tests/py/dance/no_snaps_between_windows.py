import glob, json, os, sys, h5py, numpy as np
# SMPL-24 parents, choreo_datasets' table (the harness's environment).
P = json.loads(os.environ["CHOREOD_SMPL24_PARENTS"])
def bones(j):
    return j[:, 1:] - j[:, P[1:]]
def max_turn(j):
    b = bones(j.astype(np.float64))
    c = np.linalg.norm(np.cross(b[1:], b[:-1]), axis=-1)
    return np.degrees(np.arctan2(c, (b[1:] * b[:-1]).sum(-1))).max()
f = h5py.File(sys.argv[1], "r")
j = f["motion/joints"][...]
fps = float(f["motion"].attrs["fps"])
assert fps == 30.0 and j.shape[0] == round(153.15 * 30), (fps, j.shape)
# The package's source: one clip (.npy) or a library source folder (every clip's .npy).
clips = [np.load(p) for p in (sorted(glob.glob(os.path.join(sys.argv[2], "*.npy")))
                              if os.path.isdir(sys.argv[2]) else [sys.argv[2]])]
src = max(max_turn(c) for c in clips)
got = max_turn(j)
print(f"largest bone turn per frame: dance {got:.1f} deg, source {src:.1f} deg")
# 1.24: the exemplar's fastest replay (its README, x0.625 to x1.239); the library's warp plays
# a moment up to 1.6x, but its source clips turn a bone by up to 84 degrees (flips it never
# plays), so the 60 degrees bind;
# 180/74: the stitcher's fade of at most 180 degrees over a 75-frame overlap; 1 degree for the
# rigid fit and the foot lock, which move joints by millimetres.
bound = min(60.0, 1.24 * src + 180 / 74 + 1.0)
assert got <= bound, f"a bone turns {got:.1f} deg in one frame (bound {bound:.1f})"
# Rigid: every bone keeps its length to 0.1 mm (the rigid fit's output in f32).
length = np.linalg.norm(bones(j.astype(np.float64)), axis=-1)
spread = (length.max(0) - length.min(0)).max()
assert spread < 1e-4, f"bone lengths vary by {spread * 1000:.2f} mm"
# Toes (SMPL 10, 11) never below the package's floor, y = 0 (the exemplar's source loop, and
# every library clip once the package gives it SMPL's pelvis: pkg_library.one_body; the raw
# library-source clips go to -4.5 cm, so their minimum is not the floor): a window's x0 is a
# weighted mean of the package's poses, so no joint of it is lower; the stitcher keeps each
# frame no lower than its two windows, and the rigid fit no lower than the stitched frame.
# 1 mm for float32 and the sampler's last step.
low = j[:, [10, 11], 1].min()
assert low >= -0.001, f"toes at {low:.4f} m"
print("ok")
