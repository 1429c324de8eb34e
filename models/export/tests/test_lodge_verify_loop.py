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
    return {"global_x0": rng.uniform(-1, 1, (g, 104, 139)).astype(np.float32),
            "local_x0": rng.uniform(-1, 1, (n, 256, 139)).astype(np.float32),
            "features": rng.normal(size=(frames, 139)).astype(np.float32),
            "joints": rng.normal(size=(frames, 22, 3)).astype(np.float32)}


class Compare(unittest.TestCase):
    def setUp(self):
        self.a = dances(np.random.default_rng(0))
        self.b = {k: v.copy() for k, v in self.a.items()}

    def test_equal_passes(self):
        r = V.compare(self.a, self.b)
        self.assertTrue(r["ok"])
        self.assertEqual(r["failed"], [])
        self.assertTrue(all(v == 0 for v in r["figures"].values()))

    def test_figures(self):
        self.b["global_x0"][1, 3, 7] += 5e-4
        self.b["local_x0"][4, 255, 138] -= 2e-3
        self.b["joints"][10, 21] += np.array([3e-3, 0, 4e-3], np.float32)  # 5 mm
        r = V.compare(self.a, self.b)
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
        r = V.compare(self.a, self.b)
        self.assertEqual(r["failed"], ["features_p999"])
        # 0.05 % off by 5e-3: the percentile stays under its bar, the max too.
        b = {k: v.copy() for k, v in self.a.items()}
        b["features"].reshape(-1)[: int(flat.size * 0.0005)] += 5e-3
        r = V.compare(self.a, b)
        self.assertTrue(r["ok"], r)
        self.assertAlmostEqual(r["figures"]["features_max"], 5e-3, delta=1e-6)

    def test_nan_fails(self):
        self.b["features"][0, 0] = np.nan
        self.assertIn("features_max", V.compare(self.a, self.b)["failed"])

    def test_shapes_must_agree(self):
        self.b["local_x0"] = self.b["local_x0"][:4]
        with self.assertRaises(E.ExportError):
            V.compare(self.a, self.b)


if __name__ == "__main__":
    unittest.main()
