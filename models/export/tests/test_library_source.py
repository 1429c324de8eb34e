"""The dance library's retarget (models/packages/pkg_library_source.py) and the committed library
(models/packages/library-source/): one body, directions kept, floor, facing, exact 30 fps.

    .venv/bin/python -m unittest discover -s models/export/tests -t models/export/tests

No ../shared needed: synthetic motions and the committed .npy files.
"""

from __future__ import annotations

import json
import sys
import unittest
from pathlib import Path

import numpy as np

PACKAGES = Path(__file__).resolve().parents[2] / "packages"
sys.path.insert(0, str(PACKAGES))

import pkg_common as C  # noqa: E402
import pkg_library_source as L  # noqa: E402

LIBRARY = PACKAGES / "library-source"


def smpl_motion(frames: int = 40, seed: int = 0) -> np.ndarray:
    """SMPL FK (EDGE vis.py rest offsets) of smooth random poses (each axis-angle component a
    sine of up to 0.5 rad at 0.2-1 Hz, 30 fps) along a random root path: a motion on SMPL's
    own body that turns no bone by more than ~10 degrees per frame."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None, None] / 30.0
    amp = rng.uniform(0.0, 0.5, (1, C.N_JOINTS, 3))
    freq = rng.uniform(0.2, 1.0, (1, C.N_JOINTS, 3))
    phase = rng.uniform(0.0, 2 * np.pi, (1, C.N_JOINTS, 3))
    poses = amp * np.sin(2 * np.pi * freq * t + phase)
    root = np.cumsum(rng.normal(0.0, 0.02, (frames, 3)), axis=0) + np.array([0.3, 0.95, -0.2])
    return C.smpl_forward_kinematics(poses, root)


def other_body(joints: np.ndarray, seed: int = 1) -> np.ndarray:
    """The same motion on another body: every bone scaled by its own factor (0.7-1.4), walked
    from the root in tree order, so each bone keeps its direction; legs 1.25 times SMPL's."""
    k = np.random.default_rng(seed).uniform(0.7, 1.4, C.N_JOINTS)
    k[[L.LKNEE, L.RKNEE, L.LANKLE, L.RANKLE]] = 1.25  # a longer-legged dancer
    out = joints.copy()
    for j, p in enumerate(C.SMPL_PARENTS):
        if p >= 0:
            out[:, j] = out[:, p] + k[j] * (joints[:, j] - joints[:, p])
    return out


def bone_vectors(joints: np.ndarray) -> np.ndarray:
    return np.stack([joints[:, j] - joints[:, p] for p, j in L.BONES], axis=1)


class Retarget(unittest.TestCase):
    def test_every_bone_gets_the_smpl_rest_length(self):
        src = other_body(smpl_motion())
        lengths = np.linalg.norm(bone_vectors(L.retarget(src)), axis=-1)
        # float64 arithmetic on metre-scale values: 1e-12 m.
        np.testing.assert_allclose(lengths, np.broadcast_to(L.REST_LENGTHS[1:], lengths.shape), atol=1e-12)

    def test_directions_are_the_sources(self):
        src = other_body(smpl_motion())
        a, b = bone_vectors(L.retarget(src)), bone_vectors(src)
        cos = (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
        self.assertGreater(cos.min(), 0.9999)

    def test_another_body_comes_back_as_smpl(self):
        """Retargeting a rescaled SMPL motion gives the SMPL motion back (root-relative), and
        the root path scaled by SMPL's leg length over the source's."""
        smpl = smpl_motion()
        src = other_body(smpl)
        got = L.retarget(src)
        np.testing.assert_allclose(got - got[:, :1], smpl - smpl[:, :1], atol=1e-12)
        scale = L.SMPL_LEG / L.leg_length(src)
        np.testing.assert_allclose(got[:, 0], src[:, 0] * scale, atol=1e-12)
        self.assertAlmostEqual(scale, 1 / 1.25, places=12)


class Placement(unittest.TestCase):
    def test_floor_root_and_facing(self):
        # The SMPL motion turned by 2 rad about y and lifted: ground_and_face undoes both.
        smpl = smpl_motion()
        c, s = np.cos(2.0), np.sin(2.0)
        turned = smpl @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]).T + np.array([1.0, 0.3, -2.0])
        out, info = L.ground_and_face(turned)
        self.assertAlmostEqual(out[:, L.FOOT_JOINTS, 1].min(), 0.0, places=12)
        np.testing.assert_allclose(out[0, 0, [0, 2]], 0.0, atol=1e-12)
        across = out[0, L.LHIP] - out[0, L.RHIP]
        self.assertGreater(across[0], 0.0)
        self.assertAlmostEqual(across[2], 0.0, places=12)
        # Rigid: bone lengths unchanged; and un-mirrored: toes ahead of the ankles along +z.
        np.testing.assert_allclose(np.linalg.norm(bone_vectors(out), axis=-1),
                                   np.linalg.norm(bone_vectors(turned), axis=-1), atol=1e-12)
        self.assertGreater(L.facing_check(out), 0.0)
        self.assertGreater((out[0, 10, 2] - out[0, L.LANKLE, 2]), 0.0)

    def test_z_up_sources_turn_y_up_without_mirroring(self):
        smpl = smpl_motion()
        z_up = np.stack([smpl[..., 0], -smpl[..., 2], smpl[..., 1]], axis=-1)  # y-up -> z-up, proper
        back, axis = L.to_y_up(z_up)
        self.assertEqual(axis, "+z")
        np.testing.assert_allclose(back, smpl, atol=1e-12)


class Resample(unittest.TestCase):
    def test_integer_ratios_are_exact_on_a_sine(self):
        for fps_in in (120.0, 60.0, 30.0):
            t = np.arange(int(3.0 * fps_in) + 1) / fps_in
            x = np.sin(2 * np.pi * 1.7 * t)[:, None, None] * np.ones((1, 2, 3))
            got = L.resample(x, fps_in)
            t30 = np.arange(91) / 30.0
            self.assertEqual(got.shape[0], 91, fps_in)
            np.testing.assert_allclose(got[:, 0, 0], np.sin(2 * np.pi * 1.7 * t30), atol=1e-12)

    def test_other_rates_interpolate_between_frames(self):
        t = np.arange(101) / 50.0
        x = (3.0 * t)[:, None, None] * np.ones((1, 1, 3))  # linear: interpolation is exact
        got = L.resample(x, 50.0)
        np.testing.assert_allclose(got[:, 0, 0], 3.0 * np.arange(got.shape[0]) / 30.0, atol=1e-12)
        self.assertEqual(got.shape[0], 61)


class Glitches(unittest.TestCase):
    def test_a_flipped_bone_is_cut_out(self):
        m = smpl_motion(frames=400)
        m[200, 20] = 2 * m[200, 18] - m[200, 20]  # left forearm turned 180 degrees for one frame
        pieces, glitches = L.split_at_glitches(m)
        self.assertEqual(glitches, [199, 200])
        self.assertEqual(pieces, [(0, 200 - L.GLITCH_MARGIN), (201 + L.GLITCH_MARGIN, 400)])
        clean, none = L.split_at_glitches(smpl_motion(frames=50))
        self.assertEqual((clean, none), ([(0, 50)], []))


@unittest.skipUnless((LIBRARY / "clips.json").exists(), "library-source/ not built")
class CommittedLibrary(unittest.TestCase):
    """The committed library itself: one body, on the floor, facing +z, as clips.json says."""

    @classmethod
    def setUpClass(cls):
        cls.meta = json.loads((LIBRARY / "clips.json").read_text())
        cls.clips = {c["name"]: np.load(LIBRARY / c["file"], allow_pickle=False) for c in cls.meta["clips"]}

    def test_one_skeleton_to_1e_5_m(self):
        # float32 storage of coordinates up to ~10 m: ~1e-6 m per coordinate; 1e-5 m allowed.
        self.assertEqual(self.meta["fps"], 30.0)
        for name, j in self.clips.items():
            self.assertEqual(j.dtype, np.float32)
            self.assertEqual(j.shape[1:], (24, 3), name)
            lengths = np.linalg.norm(bone_vectors(j.astype(np.float64)), axis=-1)
            self.assertLess(np.abs(lengths - L.REST_LENGTHS[1:]).max(), 1e-5, name)

    def test_floor_facing_and_frame_counts(self):
        for c in self.meta["clips"]:
            j = self.clips[c["name"]].astype(np.float64)
            self.assertEqual(j.shape[0], c["frames"], c["name"])
            self.assertAlmostEqual(j[:, L.FOOT_JOINTS, 1].min(), 0.0, places=5)
            np.testing.assert_allclose(j[0, 0, [0, 2]], 0.0, atol=1e-6)
            across = j[0, L.LHIP] - j[0, L.RHIP]
            self.assertGreater(across[0], 0.0, c["name"])
            self.assertLess(abs(across[2]), 1e-5, c["name"])
            self.assertGreater(L.facing_check(j), 0.0, c["name"])
            self.assertGreater((j[:, 15, 1] - j[:, 0, 1]).mean(), 0.0, c["name"])  # upright
            turns = L.bone_turns_deg(j)
            self.assertLessEqual(turns.max(), L.GLITCH_TURN_DEG, c["name"])
            self.assertAlmostEqual(turns.max(), c["max_bone_turn_deg_per_frame"], places=1)


if __name__ == "__main__":
    unittest.main()
