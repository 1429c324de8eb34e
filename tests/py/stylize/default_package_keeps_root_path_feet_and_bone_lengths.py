import json, os, sys, h5py, numpy as np
PARENTS = json.loads(os.environ["CHOREOD_T2M22_PARENTS"])
with h5py.File(sys.argv[1], "r") as f:
    j = f["motion/joints"][:].astype(np.float64)
c = np.load(sys.argv[2]).astype(np.float64)
assert j.shape == c.shape, (j.shape, c.shape)
root = np.abs(j[:, 0] - c[:, 0]).max()
feet = np.abs(j[:, [7, 8, 10, 11]] - c[:, [7, 8, 10, 11]]).max()
bl = lambda p: np.linalg.norm(p[:, 1:] - p[:, PARENTS[1:]], axis=-1)
lengths = np.abs(bl(j) - bl(c)).max()
arms = np.abs(j[:, 16:22] - c[:, 16:22]).max()
# The bound: <= 1 cm root drift over the clip; feet and bone lengths pass through
# (float32 on metre-scale positions: 1e-4 m). And the style did something: arms moved > 5 cm.
assert root < 1e-2 and feet < 1e-4 and lengths < 1e-4 and arms > 0.05, (root, feet, lengths, arms)
print(f"ok root {root:.1e} m, feet {feet:.1e} m, bone lengths {lengths:.1e} m, arms moved {arms:.2f} m")
