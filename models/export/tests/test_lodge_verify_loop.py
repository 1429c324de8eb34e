"""lodge_verify_loop.py's parts that need no torch: the official window counts, the noise file's
layout, the order the official loop takes its draws in, and the figures with their bars.

    .venv/bin/python -m unittest discover -s models/export/tests -t models/export/tests

The loop itself needs torch and a LODGE clone (models/export/README.md).
"""

from __future__ import annotations

import sys
import unittest
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import lodge as E  # noqa: E402
import lodge_verify_loop as V  # noqa: E402


class WindowCounts(unittest.TestCase):
    def test_official_counts(self):
        # infer_lodge.py:211-218: the tail under 256 dropped, one Global per 4 Local, rounded up.
        self.assertEqual(V.window_counts(1024), (1, 4))
        self.assertEqual(V.window_counts(1376), (2, 5))
        self.assertEqual(V.window_counts(2047), (2, 7))
        self.assertEqual(V.window_counts(2048), (2, 8))
        self.assertEqual(V.window_counts(2304), (3, 9))

    def test_short_songs_are_refused(self):
        with self.assertRaises(E.ExportError):
            V.window_counts(1023)


class Noise(unittest.TestCase):
    def test_layout_is_choreods(self):
        n = V.draw_noise(3, 1376, steps=4)
        self.assertEqual(n["global_xT"].shape, (2, 104, 139))
        self.assertEqual(n["local_xT"].shape, (5, 256, 139))
        self.assertEqual(n["local_style"].shape, (4, 2, 5, 256))
        self.assertTrue(all(a.dtype == np.float32 for a in n.values()))
        again = V.draw_noise(3, 1376, steps=4)
        self.assertTrue(all(np.array_equal(n[k], again[k]) for k in n))

    def test_official_order(self):
        n = V.draw_noise(0, 1024, steps=3)
        draws = V.official_order(n)
        self.assertEqual(len(draws), 2 + 2 * 3)
        self.assertIs(draws[0], n["global_xT"])
        self.assertIs(draws[1], n["local_xT"])
        # Per step: the unconditional call's style noise (branch 0), then the conditional one's.
        for step in range(3):
            np.testing.assert_array_equal(draws[2 + 2 * step], n["local_style"][step, 0])
            np.testing.assert_array_equal(draws[3 + 2 * step], n["local_style"][step, 1])


def dances(rng, g=2, n=5, frames=1280):
    # The in-painting's layout (Local_Module.py:206-226): contacts and rotations of the end rows,
    # the two keyframe chunks and their mirrors; the root translation (columns 4-6) free.
    mask = np.zeros((n, 256, 139), np.float32)
    for rows in (np.r_[0:4, 252:256, 28:36, 156:164], V.MIRRORED_ROWS):
        mask[:, rows, :4] = 1
        mask[:, rows, 7:] = 1
    return {"global_x0": rng.uniform(-1, 1, (g, 104, 139)).astype(np.float32),
            "local_x0": rng.uniform(-1, 1, (n, 256, 139)).astype(np.float32),
            "features": rng.normal(size=(frames, 139)).astype(np.float32),
            "joints": rng.normal(size=(frames, 22, 3)).astype(np.float32),
            "constraint_value": rng.uniform(-1, 1, (n, 256, 139)).astype(np.float32) * mask,
            "constraint_mask": mask}


class Compare(unittest.TestCase):
    def setUp(self):
        self.a = dances(np.random.default_rng(0))
        self.b = {k: v.copy() for k, v in self.a.items()}

    def compare(self, b=None):
        """choreod `b` against the official loop `a`, the official in-painting built from the
        same keyframes being `a`'s."""
        return V.compare(self.a, self.b if b is None else b, self.a)

    def test_equal_passes(self):
        r = self.compare()
        self.assertTrue(r["ok"])
        self.assertEqual(r["failed"], [])
        self.assertTrue(all(v == 0 for v in r["figures"].values()))

    def test_copied_and_mirrored_rows_have_their_own_bars(self):
        # A mirrored row off by 5e-6: under its bar (1e-5), over the copied rows' (1e-6).
        self.b["constraint_value"][3, 61, 20] += 5e-6
        r = self.compare()
        self.assertTrue(r["ok"], r)
        self.assertAlmostEqual(r["figures"]["constraint_mirrored"], 5e-6, delta=1e-7)
        self.assertEqual(r["figures"]["constraint_copied"], 0)
        # A copied keyframe row (the first chunk) off by 2e-6 fails.
        self.b["constraint_value"][0, 28, 10] += 2e-6
        r = self.compare()
        self.assertEqual(r["failed"], ["constraint_copied"])
        self.assertAlmostEqual(r["figures"]["constraint_copied"], 2e-6, delta=1e-7)

    def test_values_outside_the_mask_do_not_count_but_the_mask_does(self):
        self.b["constraint_value"][1, 100, 50] = 7.0  # a free row
        self.b["constraint_value"][1, 0, 5] = 7.0  # the root translation of an end row
        self.assertTrue(self.compare()["ok"])
        self.b["constraint_mask"][2, 30, 5] = 1
        r = self.compare()
        self.assertEqual(r["failed"], ["constraint_mask"])
        self.assertEqual(r["figures"]["constraint_mask"], 1)

    def test_the_in_loop_difference_is_context_not_a_bar(self):
        built = {k: v.copy() for k, v in self.a.items()}
        official = {k: v.copy() for k, v in self.a.items()}
        official["constraint_value"][0, 0, 0] += 1e-3  # the official loop's own keyframes differ
        r = V.compare(official, self.b, built)
        self.assertTrue(r["ok"], r)
        self.assertAlmostEqual(r["context"]["constraint_copied_in_loop"], 1e-3, delta=1e-7)

    def test_nan_in_the_constraint_fails(self):
        self.b["constraint_value"][0, 190, 8] = np.nan
        self.assertEqual(self.compare()["failed"], ["constraint_mirrored"])

    def test_figures(self):
        self.b["global_x0"][1, 3, 7] += 5e-4
        self.b["local_x0"][4, 255, 138] -= 2e-3
        self.b["joints"][10, 21] += np.array([3e-3, 0, 4e-3], np.float32)  # 5 mm
        r = self.compare()
        f = r["figures"]
        self.assertAlmostEqual(f["global_x0"], 5e-4, delta=1e-7)
        self.assertAlmostEqual(f["local_x0"], 2e-3, delta=1e-7)
        self.assertAlmostEqual(f["joints_mm"], 5.0, delta=1e-3)
        self.assertEqual(r["failed"], ["local_x0", "joints_mm"])
        self.assertFalse(r["ok"])

    def test_feature_percentile_and_max(self):
        # 0.2 % of the values off by 2e-3: above the 99.9th percentile's bar, under the max's.
        flat = self.b["features"].reshape(-1)
        flat[: int(flat.size * 0.002)] += 2e-3
        r = self.compare()
        self.assertEqual(r["failed"], ["features_p999"])
        # 0.05 % off by 5e-3: the percentile stays under its bar, the max too.
        b = {k: v.copy() for k, v in self.a.items()}
        b["features"].reshape(-1)[: int(flat.size * 0.0005)] += 5e-3
        r = self.compare(b)
        self.assertTrue(r["ok"], r)
        self.assertAlmostEqual(r["figures"]["features_max"], 5e-3, delta=1e-6)

    def test_nan_fails(self):
        self.b["features"][0, 0] = np.nan
        self.assertIn("features_max", self.compare()["failed"])

    def test_shapes_must_agree(self):
        self.b["local_x0"] = self.b["local_x0"][:4]
        with self.assertRaises(E.ExportError):
            self.compare()


if __name__ == "__main__":
    unittest.main()
