"""The MCM-LDM exporter's parts that need no torch: argument checks, weight selection, Mean/Std
checks, the manifest, publishing, and the numpy recover_from_ric against the official one.

    .venv/bin/python -m unittest discover -s models/export/tests -t models/export/tests

(project .venv: numpy, onnx, onnxruntime; no torch). What only the local check covers — the ONNX
export itself and its equality with the official PyTorch loop — is in models/export/README.md.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import sys
import tempfile
import tomllib
import unittest
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import mcm_ldm as E  # noqa: E402


def weights(seed: int, *names: str) -> dict:
    rng = np.random.default_rng(seed)
    return {n: rng.standard_normal((3, 2)).astype(np.float32) for n in names}


class SelectWeights(unittest.TestCase):
    NAMES = {"denoiser": "denoiser.ckpt", "vae": "vae7.ckpt", "motionclip": "motionclip.pth.tar"}

    def checkpoints(self):
        vae, den, enc = weights(1, "a.w", "b.w"), weights(2, "c.w"), weights(3, "d.w")
        full = {**{"vae." + k: v for k, v in vae.items()}, **{"denoiser." + k: v for k, v in den.items()},
                **{"motionclip.encoder." + k: v for k, v in enc.items()},
                "motionclip.decoder.x": np.zeros(1), "t2m_textencoder.y": np.zeros(1)}
        return vae, den, enc, {"denoiser": full, "vae": {"vae." + k: v for k, v in vae.items()},
                               "motionclip": {"encoder." + k: v for k, v in enc.items()}}

    def test_all_from_denoiser_ckpt_as_the_demo_loads_them(self):
        vae, den, enc, ckpts = self.checkpoints()
        ckpts["vae"] = {"vae." + k: v + 1e-3 for k, v in vae.items()}  # the fall-back differs
        chosen, notes = E.select_weights(ckpts, self.NAMES)
        self.assertEqual(set(chosen), {"vae", "denoiser", "motionclip_encoder"})
        for got, want in ((chosen["vae"], vae), (chosen["denoiser"], den), (chosen["motionclip_encoder"], enc)):
            self.assertEqual(got.keys(), want.keys())
            for k in want:
                np.testing.assert_array_equal(got[k], want[k])
        self.assertEqual(len(notes), 1)
        self.assertIn("vae7.ckpt", notes[0])
        self.assertIn("differs", notes[0])

    def test_identical_sources_give_no_note(self):
        vae, _, _, ckpts = self.checkpoints()
        ckpts["vae"] = {"vae." + k: v + 1e-7 for k, v in vae.items()}  # float noise only
        _, notes = E.select_weights(ckpts, self.NAMES)
        self.assertEqual(notes, [])

    def test_fall_back_files(self):
        vae, _, enc, ckpts = self.checkpoints()
        ckpts["denoiser"] = {k: v for k, v in ckpts["denoiser"].items() if k.startswith("denoiser.")}
        chosen, notes = E.select_weights(ckpts, self.NAMES)
        np.testing.assert_array_equal(chosen["vae"]["a.w"], vae["a.w"])
        np.testing.assert_array_equal(chosen["motionclip_encoder"]["d.w"], enc["d.w"])
        self.assertEqual(len(notes), 2)
        self.assertTrue(all("weights from" in n for n in notes))

    def test_missing_module_is_one_clear_error(self):
        _, _, _, ckpts = self.checkpoints()
        ckpts["denoiser"] = {k: v for k, v in ckpts["denoiser"].items() if not k.startswith("denoiser.")}
        msg = r"no weights for the denoiser: expected keys 'denoiser\.\*' in denoiser\.ckpt"
        with self.assertRaisesRegex(E.ExportError, msg):
            E.select_weights(ckpts, self.NAMES)

    def test_max_abs_diff(self):
        a = weights(4, "x", "y")
        b = {k: v.copy() for k, v in a.items()}
        self.assertEqual(E.max_abs_diff(a, b), 0.0)
        b["y"][1, 1] += 0.25
        self.assertAlmostEqual(E.max_abs_diff(a, b), 0.25, places=6)
        self.assertEqual(E.max_abs_diff(a, {"x": a["x"]}), float("inf"))
        self.assertEqual(E.max_abs_diff(a, {"x": a["x"], "y": a["y"][:1]}), float("inf"))


class Inputs(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.TemporaryDirectory()
        self.dir = Path(self.tmp.name)

    def tearDown(self):
        self.tmp.cleanup()

    def save(self, name: str, a) -> Path:
        path = self.dir / name
        np.save(path, a)
        return path

    def test_stats_accepted_and_rejected(self):
        mean = self.save("m.npy", np.linspace(-1, 1, E.DIM))
        std = self.save("s.npy", np.full(E.DIM, 0.5))
        m, s = E.load_stats(mean, std)
        self.assertEqual((m.dtype, s.dtype, m.shape), (np.float32, np.float32, (E.DIM,)))
        bad_std = np.full(E.DIM, 0.5)
        bad_std[17] = 0.0
        cases = {"shape (262,)": np.zeros(E.DIM - 1), "finite": np.full(E.DIM, np.nan),
                 "int64": np.zeros(E.DIM, np.int64)}
        for msg, a in cases.items():
            with self.subTest(msg), self.assertRaisesRegex(E.ExportError, "bad.npy: mean must be 263 finite"):
                E.load_stats(self.save("bad.npy", a), std)
        with self.assertRaisesRegex(E.ExportError, r"s.npy: std must be > 0 everywhere \(dimension 17"):
            E.load_stats(mean, self.save("s.npy", bad_std))
        (self.dir / "junk.npy").write_bytes(b"\x93NUMPY garbage")
        with self.assertRaisesRegex(E.ExportError, "junk.npy: not a readable .npy file"):
            E.load_stats(self.dir / "junk.npy", std)
        # pickled object arrays are refused, never executed
        np.save(self.dir / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
        with self.assertRaisesRegex(E.ExportError, "obj.npy: not a readable .npy file"):
            E.load_stats(self.dir / "obj.npy", std)

    def test_repo_and_output_checks(self):
        with self.assertRaisesRegex(E.ExportError, "not an MCM-LDM clone .missing configs/config_mld_humanml3d.yaml"):
            E.check_repo(self.dir)
        for f in E.REPO_FILES:
            (self.dir / f).parent.mkdir(parents=True, exist_ok=True)
            (self.dir / f).touch()
        E.check_repo(self.dir)
        E.check_output(self.dir / "pkg")
        with self.assertRaisesRegex(E.ExportError, "already exists"):
            E.check_output(self.dir)
        with self.assertRaisesRegex(E.ExportError, "no such directory"):
            E.check_output(self.dir / "nope" / "pkg")

    def test_features_for_verify(self):
        self.assertEqual(E.load_features(self.save("c.npy", np.zeros((6, E.DIM), np.float64))).dtype, np.float32)
        for a in (np.zeros((6, 262)), np.zeros(E.DIM), np.full((3, E.DIM), np.inf)):
            with self.assertRaisesRegex(E.ExportError, "expected finite HumanML3D features"):
                E.load_features(self.save("c.npy", a))

    def test_arguments(self):
        files = {n: self.dir / f"{n}.bin" for n in ("vae", "denoiser", "motionclip", "mean", "std")}
        for p in files.values():
            p.touch()
        base = ["--repo", str(self.dir), "-o", str(self.dir / "pkg")] + [
            x for n, p in files.items() for x in (f"--{n}", str(p))]
        a = E.parse_args(base + ["--verify", "--choreod", sys.executable])
        self.assertTrue(a.verify)
        self.assertFalse(a.allow_pickle)

        def usage_error(argv) -> str:
            err = io.StringIO()
            with contextlib.redirect_stderr(err), self.assertRaises(SystemExit) as cm:
                E.parse_args(argv)
            self.assertEqual(cm.exception.code, 2)
            return err.getvalue()

        missing = str(Path(files["std"]).with_name("no-such-choreod"))
        self.assertIn(f"--verify runs `choreod stylize`: {missing} is not an executable",
                      usage_error(base + ["--verify", "--choreod", missing]))
        self.assertEqual(E.parse_args(base + ["--choreod", sys.executable]).choreod, sys.executable)
        files["std"].unlink()
        self.assertIn(f"--std {files['std']}: no such file", usage_error(base))
        files["std"].touch()
        self.assertIn("--pair needs --verify", usage_error(base + ["--pair", str(files["mean"]), str(files["std"])]))
        self.assertIn("--pair nope.npy: no such file",
                      usage_error(base + ["--verify", "--pair", "nope.npy", str(files["std"])]))


class Manifest(unittest.TestCase):
    def test_contract_and_hashes(self):
        rng = np.random.default_rng(0)
        mean = rng.standard_normal(E.DIM).astype(np.float32)
        std = rng.uniform(0.01, 2.0, E.DIM).astype(np.float32)
        with tempfile.TemporaryDirectory() as tmp:
            out, src = Path(tmp) / "pkg", Path(tmp) / "denoiser.ckpt"
            out.mkdir()
            src.write_bytes(b"weights")
            for role, (file, _, _) in E.COMPONENTS.items():
                (out / file).write_bytes(role.encode())
            path = E.write_package_manifest(out, mean, std, {"denoiser": src})
            text = path.read_text()
            with open(path, "rb") as f:
                m = tomllib.load(f)
        self.assertIn(f"denoiser.ckpt sha256 {hashlib.sha256(b'weights').hexdigest()}", text)
        self.assertEqual((m["format"], m["format_version"], m["task"]), ("choreod-model", 1, "style-transfer"))
        mo = m["motion"]
        self.assertEqual((mo["fps"], mo["skeleton"], mo["representation"], mo["dim"]),
                         (20.0, "t2m22", "humanml3d263", 263))
        # T + 14 VAE query tokens <= 500 learned positions
        self.assertEqual(mo["max_frames"], 486)
        np.testing.assert_array_equal(np.asarray(mo["mean"], np.float32), mean)  # inline, bit-exact
        np.testing.assert_array_equal(np.asarray(mo["std"], np.float32), std)
        self.assertEqual(m["diffusion"], {"train_steps": 1000, "beta_schedule": "scaled_linear", "beta_start": 0.00085,
                                          "beta_end": 0.012, "prediction": "epsilon", "clip_sample": False})
        sm = m["sampler"]
        self.assertEqual((sm["kind"], sm["steps"], sm["eta"], sm["steps_offset"], sm["set_alpha_to_one"],
                          sm["guidance"], sm["inversion_steps"]), ("ddim", 50, 0.0, 1, False, 2.5, 30))
        self.assertEqual(list(m["components"]), ["vae_encoder", "vae_decoder", "style_encoder", "denoiser"])
        for role, comp in m["components"].items():
            self.assertEqual(comp["sha256"], hashlib.sha256(role.encode()).hexdigest())
        den = m["components"]["denoiser"]
        self.assertEqual([(i["name"], i["dtype"], i["shape"]) for i in den["inputs"]], [
            ("x_t", "float32", ["N", 7, 256]), ("t", "int64", ["N"]),
            ("content", "float32", ["N", 7, 256]), ("trajectory", "float32", ["N", "T", 3]),
            ("mask", "float32", ["N", "T"]), ("style", "float32", ["N", 512])])
        self.assertEqual(den["outputs"], [{"name": "pred", "dtype": "float32", "shape": ["N", 7, 256]}])
        enc = m["components"]["vae_encoder"]
        self.assertEqual([i["shape"] for i in enc["inputs"]], [["N", "T", 263], ["N", "T"]])
        self.assertEqual(enc["outputs"][0]["shape"], ["N", 7, 256])
        self.assertEqual(m["components"]["style_encoder"]["outputs"][0]["shape"], ["N", 512])

    def test_publish_moves_a_complete_directory(self):
        with tempfile.TemporaryDirectory() as tmp:
            staging, out = Path(tmp) / ".pkg.partial-1", Path(tmp) / "pkg"
            staging.mkdir()
            (staging / "a.onnx").write_bytes(b"a")
            E.publish(staging, out)
            self.assertEqual(sorted(p.name for p in Path(tmp).iterdir()), ["pkg"])
            self.assertEqual((out / "a.onnx").read_bytes(), b"a")


class RecoverFromRic(unittest.TestCase):
    def test_matches_the_official_function(self):
        ref = np.load(HERE / "recover_from_ric.npz")
        got = E.recover_from_ric(ref["features"])
        self.assertEqual(got.shape, (24, 22, 3))
        # The reference is torch float32 through 24 frames of cumulative sums (~1e-7 relative per
        # step on metre-scale values); 1e-5 m is far below any error of the formula (a wrong sign
        # or a one-frame shift moves joints by centimetres).
        np.testing.assert_allclose(got, ref["joints"], rtol=0, atol=1e-5)

    def test_relative(self):
        d, r = E.relative(np.array([1.0, 2.5]), np.array([1.0, 2.0]))
        self.assertEqual((d, r), (0.5, 0.25))


if __name__ == "__main__":
    unittest.main()
