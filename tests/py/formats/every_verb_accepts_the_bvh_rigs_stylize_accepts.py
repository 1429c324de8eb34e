import sys, numpy as np
a, b = np.load(sys.argv[1]), np.load(sys.argv[2])
# 2752 frames at 120 fps -> 459 at 20 fps -> 458 feature frames.
assert a.shape == b.shape == (458, 263), (a.shape, b.shape)
assert np.isfinite(a).all() and np.isfinite(b).all()
# Root height: from the hips and legs (also the scale to HumanML3D's skeleton), which both rigs
# place on the same joints.
assert np.array_equal(a[:, 3], b[:, 3]), np.abs(a[:, 3] - b[:, 3]).max()
# The spine is placed differently (CMU: Spine and midpoints; Mixamo: its three spine joints),
# and with it the facing of the rest: the two are different motions on t2m-22.
assert np.abs(a - b).max() > 0.1
print("ok")
