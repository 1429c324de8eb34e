# The style-gaussian map A from its README ("The closed form"), in numpy, on positions:
# bone vectors b_j = p_j − p_parent(j) (p_0 = (0, root_y, 0); ric slots 4..67 hold p_1..p_21),
# in decimetres; per restyled channel (upper-body bones) A(c) = m_s + (s~_s / s~_c)(c − m_c)
# with population statistics over the frames and s~ = sqrt(s² + 0.5²); the decoder keeps each
# bone's length (direction from A, length from the content) and rebuilds the positions down
# the t2m kinematic tree. Everything else passes through.
import json, os, numpy as np
# HumanML3D paramUtil t2m_kinematic_chain as parents: choreo_datasets' table (the harness's
# environment).
PARENTS = json.loads(os.environ["CHOREOD_T2M22_PARENTS"])
UPPER = [3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21]
def positions(f):
    p = np.zeros((len(f), 22, 3))
    p[:, 0, 1] = f[:, 3]
    p[:, 1:] = f[:, 4:67].reshape(-1, 21, 3)
    return p
def bones(f):
    p = positions(f)
    return np.stack([p[:, j] - p[:, PARENTS[j]] for j in range(1, 22)], axis=1)
def closed_form(content, style):
    bc, bs = 10.0 * bones(content.astype(np.float64)), 10.0 * bones(style.astype(np.float64))
    out = bc.copy()
    for j in UPPER:
        c, st = bc[:, j - 1], bs[:, j - 1]
        gain = np.sqrt(st.std(0) ** 2 + 0.25) / np.sqrt(c.std(0) ** 2 + 0.25)
        out[:, j - 1] = st.mean(0) + gain * (c - c.mean(0))
    length = np.linalg.norm(bc, axis=-1, keepdims=True)
    out = out / np.linalg.norm(out, axis=-1, keepdims=True) * length / 10.0
    p = positions(content.astype(np.float64))
    for j in range(1, 22):
        p[:, j] = p[:, PARENTS[j]] + out[:, j - 1]
    f = content.astype(np.float64).copy()
    f[:, 4:67] = p[:, 1:].reshape(len(f), 63)
    return f
