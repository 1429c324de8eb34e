"""The LODGE exporter's parts that need no torch and no LODGE: the pickle gate in front of
torch's unpickler, sizes from weight shapes, the Normalizer checks and the manifest.

    .venv/bin/python -m unittest discover -s models/export/tests -t models/export/tests

The export itself and its equality with the official networks need torch and a LODGE clone:
`lodge.py --verify` covers them (models/export/README.md).
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import sys
import tempfile
import tomllib
import types
import unittest
import zipfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

import lodge as L  # noqa: E402


class Hostile:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def torch_zip(path: Path, pkl: bytes) -> Path:
    """A file in torch.save's zip layout holding `pkl` as its data.pkl."""
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("archive/data.pkl", pkl)
        z.writestr("archive/version", "3\n")
    return path


# What torch.save writes for a Normalizer: the class by its module path, tensors rebuilt by
# torch._utils._rebuild_tensor_v2 from a persistent storage id naming torch.FloatStorage.
BENIGN = (b"\x80\x02cdld.data.utils.preprocess\nNormalizer\nq\x00)\x81q\x01}q\x02X\x06\x00\x00\x00scalerq\x03"
          b"ctorch._utils\n_rebuild_tensor_v2\nq\x04ctorch\nFloatStorage\nq\x05\x86q\x06sb.")


class PickleGate(unittest.TestCase):
    def setUp(self):
        self.tmp = Path(tempfile.mkdtemp())

    def test_the_normalizer_layout_passes(self):
        names = L.pickle_globals(BENIGN)
        self.assertIn(("dld.data.utils.preprocess", "Normalizer"), names)
        self.assertIn(("torch", "FloatStorage"), names)
        L.check_pickle_globals(torch_zip(self.tmp / "ok.pth", BENIGN))

    def test_a_reduce_to_os_system_is_refused_at_every_protocol(self):
        for proto in (2, 4, 5):
            with self.subTest(protocol=proto):
                path = torch_zip(self.tmp / f"evil{proto}.pth", pickle.dumps({"scaler": Hostile()}, protocol=proto))
                with self.assertRaisesRegex(L.ExportError, r"refers to (posix|nt)\.system"):
                    L.check_pickle_globals(path)

    def test_a_stack_global_of_computed_names_is_refused(self):
        # STACK_GLOBAL whose names come from the memo (BINGET), not from literal strings.
        data = b"\x80\x04\x8c\x08builtinsq\x00\x8c\x04evalq\x01h\x00h\x01\x93."
        self.assertIn(("?", "STACK_GLOBAL of computed names"), L.pickle_globals(data))
        with self.assertRaisesRegex(L.ExportError, "refusing"):
            L.check_pickle_globals(torch_zip(self.tmp / "memo.pth", data))

    def test_not_a_zip_truncated_or_damaged_is_refused(self):
        raw = self.tmp / "raw.pth"
        raw.write_bytes(pickle.dumps({"a": 1}))
        with self.assertRaisesRegex(L.ExportError, "not a PyTorch zip file"):
            L.check_pickle_globals(raw)
        whole = torch_zip(self.tmp / "whole.pth", BENIGN).read_bytes()
        cut = self.tmp / "cut.pth"
        cut.write_bytes(whole[: len(whole) // 2])
        with self.assertRaises(L.ExportError):
            L.check_pickle_globals(cut)
        with self.assertRaisesRegex(L.ExportError, "damaged pickle"):
            L.check_pickle_globals(torch_zip(self.tmp / "damaged.pth", BENIGN[:-12]))
        empty = self.tmp / "empty.pth"
        with zipfile.ZipFile(empty, "w") as z:
            z.writestr("archive/version", "3\n")
        with self.assertRaisesRegex(L.ExportError, "without a pickle"):
            L.check_pickle_globals(empty)


def released_shapes(kind: str, layers: int = 8, genres: int = 16, seq_len: int | None = None,
                    nfeats: int = 139) -> dict:
    """The shapes infer_sizes reads, for the released sizes (latent 512, ff 1024)."""
    seq = seq_len or (1024 if kind == "global" else 256)
    s = {"input_projection.weight": (512, nfeats), "cond_projection.weight": (512, 35),
         "null_cond_embed": (1, seq, 512), "cond_encoder.0.linear1.weight": (1024, 512), "rotary.freqs": (256,)}
    stack = layers + (1 if kind == "local" else 0)
    s.update({f"seqTransDecoder.stack.{i}.linear1.weight": (1024, 512) for i in range(stack)})
    if kind == "local":
        s["mapping.shared.0.weight"] = (512, 256)
        s.update({f"mapping.unshared.{i}.0.weight": (512, 512) for i in range(genres)})
    return s


class Sizes(unittest.TestCase):
    def test_released_global(self):
        self.assertEqual(L.infer_sizes(released_shapes("global"), "global", "g.ckpt"),
                         {"latent_dim": 512, "nfeats": 139, "cond_feature_dim": 35, "seq_len": 1024,
                          "ff_size": 1024, "num_layers": 8, "use_rotary": True})

    def test_released_local_counts_the_refine_layer_in_the_main_stack(self):
        sizes = L.infer_sizes(released_shapes("local"), "local", "l.ckpt")
        self.assertEqual((sizes["num_layers"], sizes["genre_num"], sizes["seq_len"]), (8, 16, 256))

    def test_other_layouts_are_refused_with_the_reason(self):
        cases = [
            (released_shapes("global", seq_len=256), "global", "music window of 256"),
            (released_shapes("global", nfeats=135), "global", "135 motion values"),
            (released_shapes("local", genres=10), "local", "10 genre heads"),
            ({k: v for k, v in released_shapes("global").items() if k != "null_cond_embed"}, "global",
             "no 'DanceDecoder.null_cond_embed'"),
            ({**released_shapes("local"), "mapping.shared.0.weight": (512, 128)}, "local", "takes 128"),
            ({**released_shapes("global"), "null_cond_embed": (1024, 512)}, "global", "expected rank 3"),
        ]
        for shapes, kind, message in cases:
            with self.subTest(message):
                with self.assertRaisesRegex(L.ExportError, message):
                    L.infer_sizes(shapes, kind, "x.ckpt")

    def test_split_state_notes_a_differing_twin_and_needs_the_prefix(self):
        w = np.ones((2, 2), np.float32)
        weights, notes = L.split_state({"DanceDecoder.a": w, "diffusion.model.a": w,
                                        "diffusion.master_model.a": w * 2}, "g.ckpt")
        self.assertEqual((list(weights), notes), (["a"], []))
        _, notes = L.split_state({"DanceDecoder.a": w, "diffusion.model.a": w + 1}, "g.ckpt")
        self.assertEqual(len(notes), 1)
        with self.assertRaisesRegex(L.ExportError, "no 'DanceDecoder"):
            L.split_state({"model.a": w}, "g.ckpt")


def normalizer(scale, offset, feature_range=(-1, 1), clip=True):
    scaler = types.SimpleNamespace(scale_=scale, min_=offset, feature_range=feature_range, clip=clip)
    return types.SimpleNamespace(scaler=scaler)


class Normaliser(unittest.TestCase):
    def test_arrays_come_back_unchanged(self):
        rng = np.random.default_rng(0)
        scale, offset = rng.uniform(0.1, 3, 139), rng.standard_normal(139)
        got = L.normalizer_arrays(normalizer(scale, offset), Path("n.pth"))
        self.assertTrue(np.array_equal(got[0], scale) and np.array_equal(got[1], offset))

    def test_wrong_objects_are_refused(self):
        ok = np.ones(139)
        for obj, message in ((types.SimpleNamespace(), "scale_"),
                             (normalizer(np.ones(138), ok), "scale_"),
                             (normalizer(ok, np.full(139, np.nan)), "min_"),
                             (normalizer(ok, ok, feature_range=(0, 1)), "maps to"),
                             (normalizer(ok, ok, clip=False), "clip"),
                             (normalizer(np.r_[ok[:5], 0.0, ok[6:]], ok), "scale is 0 at feature 5")):
            with self.subTest(message):
                with self.assertRaisesRegex(L.ExportError, message):
                    L.normalizer_arrays(obj, Path("n.pth"))


class Manifest(unittest.TestCase):
    def test_manifest_holds_every_section_bit_exactly(self):
        rng = np.random.default_rng(1)
        sizes = {"global": L.infer_sizes(released_shapes("global"), "global", "g"),
                 "local": L.infer_sizes(released_shapes("local"), "local", "l")}
        scale, offset = rng.uniform(0.1, 3, 139), rng.standard_normal(139)
        rest = rng.standard_normal((55, 3))
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp)
            for role, (file, _, _) in L.components(sizes).items():
                (out / file).write_bytes(role.encode())
            src = out / "epoch=2999.ckpt"
            src.write_bytes(b"weights")
            m = tomllib.loads(L.write_manifest(out, sizes=sizes, scale=scale, offset=offset, rest=rest,
                                               sources={"global": src, "local": src}).read_text())
        self.assertEqual((m["format"], m["format_version"], m["task"]), ("choreod-model", 1, "lodge"))
        self.assertEqual((m["license"]["commercial_use"], m["license"]["redistribution"]), (False, False))
        self.assertIn("non-commercial", m["license"]["name"])
        self.assertTrue(np.array_equal(m["motion"]["normalizer"]["scale"], scale))
        self.assertTrue(np.array_equal(m["motion"]["normalizer"]["offset"], offset))
        self.assertTrue(np.array_equal(np.array(m["motion"]["rest_joints"]).reshape(55, 3), rest))
        self.assertEqual((m["motion"]["fps"], m["motion"]["dim"], m["motion"]["representation"]),
                         (30.0, 139, "lodge-smplx139"))
        self.assertEqual((m["audio"]["features"], m["audio"]["librosa"], m["audio"]["dim"]), ("fact35", "0.7.2", 35))
        self.assertEqual((m["diffusion"]["beta_schedule"], m["diffusion"]["train_steps"],
                          m["diffusion"]["cumprod_dtype"], m["diffusion"]["prediction"]),
                         ("cosine", 1000, "float32", "x0"))
        self.assertEqual((m["sampler"]["kind"], m["sampler"]["steps"], m["sampler"]["eta"]), ("ddim", 50, 1.0))
        # torch.linspace(-1, 999, 51).int() reversed, as diffusion.py:265-267 builds it.
        self.assertEqual(m["sampler"]["timesteps"][:3] + m["sampler"]["timesteps"][-2:], [999, 979, 959, 39, 19])
        self.assertEqual(len(m["sampler"]["timesteps"]), 50)
        self.assertEqual(len(m["lodge"]["genres"]), 16)
        self.assertEqual(m["lodge"]["genres"][14], "Choreography")
        self.assertEqual((m["lodge"]["global"]["guidance"], m["lodge"]["global"]["keyframes"],
                          m["lodge"]["global"]["music_frames"]), (2.0, 104, 1024))
        self.assertEqual((m["lodge"]["local"]["guidance_ramp"], m["lodge"]["local"]["frames"]), ([0.0, 4.0], 256))
        den = m["components"]["local_denoiser"]
        self.assertEqual(den["sha256"], hashlib.sha256(b"local_denoiser").hexdigest())
        self.assertEqual([(i["name"], i["dtype"], i["shape"]) for i in den["inputs"]],
                         [("x_t", "float32", ["N", 256, 139]), ("t", "int64", ["N"]),
                          ("cond_hidden", "float32", ["N", 512]), ("cross_k", "float32", ["N", 9, 256, 512]),
                          ("cross_v", "float32", ["N", 9, 256, 512]),
                          ("genre", "int64", ["N"]), ("style_noise", "float32", ["N", 256])])
        # The music branch gives what the denoiser takes of it; the local stack holds 9 layers
        # (its refine layer), the global one 8.
        music = m["components"]["local_music"]["outputs"]
        self.assertEqual(music, den["inputs"][2:5])
        self.assertEqual(m["components"]["global_music"]["outputs"][1]["shape"], ["N", 8, 1024, 512])


class TinyPackage(unittest.TestCase):
    """models/packages/lodge-tiny-random-kv (made by make_lodge_fixture_package.py): its manifest
    matches its files, and each component runs with the declared tensors and reacts to each
    input the way the pipeline relies on."""

    PKG = HERE.parents[1] / "packages" / "lodge-tiny-random-kv"

    @classmethod
    def setUpClass(cls):
        import onnxruntime as ort

        cls.m = tomllib.loads((cls.PKG / "choreod-model.toml").read_text())
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        cls.sess = {role: ort.InferenceSession(str(cls.PKG / c["file"]), opts, providers=["CPUExecutionProvider"])
                    for role, c in cls.m["components"].items()}

    def feeds(self, role: str, n: int, seed: int = 0) -> dict:
        rng = np.random.default_rng(seed)
        out = {}
        for spec in self.m["components"][role]["inputs"]:
            shape = [n if d == "N" else d for d in spec["shape"]]
            if spec["name"] == "t":
                out["t"] = rng.integers(0, 1000, shape).astype(np.int64)
            elif spec["name"] == "genre":
                out["genre"] = rng.integers(0, 16, shape).astype(np.int64)
            elif spec["name"] == "keep":
                out["keep"] = np.ones(shape, np.float32)
            else:
                out[spec["name"]] = rng.standard_normal(shape).astype(np.float32)
        return out

    def call(self, role: str, feeds: dict) -> list:
        return self.sess[role].run(None, feeds)

    def test_files_match_the_manifest(self):
        self.assertEqual(self.m["task"], "lodge")
        for c in self.m["components"].values():
            self.assertEqual(hashlib.sha256((self.PKG / c["file"]).read_bytes()).hexdigest(), c["sha256"])
        for role, sess in self.sess.items():
            spec = self.m["components"][role]
            self.assertEqual([i.name for i in sess.get_inputs()], [i["name"] for i in spec["inputs"]])
            self.assertEqual([o.name for o in sess.get_outputs()], [o["name"] for o in spec["outputs"]])

    def test_rows_are_independent_and_every_input_matters(self):
        for role in ("global_denoiser", "local_denoiser"):
            f3 = self.feeds(role, 3)
            (x3,) = self.call(role, f3)
            self.assertEqual(list(x3.shape), [3, *self.m["components"][role]["outputs"][0]["shape"][1:]])
            (x1,) = self.call(role, {k: v[1:2] for k, v in f3.items()})
            # Batch rows are independent: row 1 alone equals row 1 of the batch (float32 GEMM
            # blocking may differ by rounding).
            self.assertLess(np.abs(x1[0] - x3[1]).max(), 1e-5 * np.abs(x3).max())
            for name in f3:
                changed = dict(f3)
                v = f3[name]
                # New values (a per-element change: cond_tokens pass a LayerNorm, which ignores
                # a common scale and shift).
                noise = np.random.default_rng(9).standard_normal(v.shape).astype(np.float32)
                changed[name] = {"genre": (v + 1) % 16, "t": (v + 100) % 1000}.get(name, v + noise)
                (x,) = self.call(role, changed)
                self.assertGreater(np.abs(x - x3).max(), 1e-4, f"{role}: input {name} has no effect")

    def test_the_guidance_drop_replaces_the_music_with_one_null_embedding(self):
        for role in ("global_music", "local_music"):
            f = self.feeds(role, 2)
            kept = self.call(role, f)
            f["keep"] = np.zeros(2, np.float32)
            dropped = self.call(role, f)
            for a, b in zip(kept, dropped):
                self.assertGreater(np.abs(a - b).max(), 1e-3)
                self.assertEqual(np.abs(b[0] - b[1]).max(), 0.0)  # the same for any music
            f2 = self.feeds(role, 2, seed=1)
            f2["keep"] = np.zeros(2, np.float32)
            for a, b in zip(dropped, self.call(role, f2)):
                self.assertEqual(np.abs(a - b).max(), 0.0)


class TinyPackageTokens(TinyPackage):
    """The same for models/packages/lodge-tiny-random: the same weights (seed 0) exported by the
    exporter of 385b8a9, whose music branch hands the denoiser its tokens (`cond_tokens`) instead
    of each layer's keys and values: the layout of packages exported before, which choreod
    still runs."""

    PKG = HERE.parents[1] / "packages" / "lodge-tiny-random"

    def test_both_layouts_compute_the_same_network(self):
        """Music branch then denoiser, old layout against the hoisted keys and values: the same
        function of the same inputs (measured 2.4e-7 and 0 relative; a wrong key projection
        gives far more)."""
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1
        for stage in ("global", "local"):
            den_feeds = self.feeds(f"{stage}_denoiser", 3, seed=4)
            music = self.feeds(f"{stage}_music", 3, seed=5)
            music["keep"] = np.array([1.0, 0.0, 1.0], np.float32)
            got = []
            for pkg in (self.PKG, TinyPackage.PKG):
                m = tomllib.loads((pkg / "choreod-model.toml").read_text())["components"]
                run = {r: ort.InferenceSession(str(pkg / m[r]["file"]), opts, providers=["CPUExecutionProvider"])
                       for r in (f"{stage}_music", f"{stage}_denoiser")}
                cond = dict(zip([o["name"] for o in m[f"{stage}_music"]["outputs"]],
                                run[f"{stage}_music"].run(None, music)))
                feeds = {k: v for k, v in den_feeds.items() if k in ("x_t", "t", "genre", "style_noise")}
                feeds.update(cond)
                got.append(run[f"{stage}_denoiser"].run(None, feeds)[0])
            rel = np.abs(got[0] - got[1]).max() / np.abs(got[0]).max()
            self.assertLess(rel, 1e-5, f"{stage}: the layouts differ by {rel:.2e} relative")


class Inputs(unittest.TestCase):
    def test_a_directory_that_is_not_a_clone_is_named(self):
        with tempfile.TemporaryDirectory() as tmp:
            with self.assertRaisesRegex(L.ExportError, "not a LODGE clone"):
                L.check_repo(Path(tmp))

    def test_rest_joints_must_be_55_finite_rows(self):
        with tempfile.TemporaryDirectory() as tmp:
            p = Path(tmp) / "J.npy"
            np.save(p, np.zeros((52, 3)))
            with self.assertRaisesRegex(L.ExportError, "55 x 3"):
                L.load_rest_joints(p)
            p.write_bytes(b"junk")
            with self.assertRaisesRegex(L.ExportError, "not a readable"):
                L.load_rest_joints(p)

    def test_main_reports_one_line_and_exit_1(self):
        with tempfile.TemporaryDirectory() as tmp:
            ck = Path(tmp) / "c.ckpt"
            ck.write_bytes(b"x")
            err = io.StringIO()
            old = sys.stderr
            sys.stderr = err
            try:
                code = L.main(["--repo", tmp, "--global", str(ck), "--local", str(ck), "-o", str(Path(tmp) / "p")])
            finally:
                sys.stderr = old
        self.assertEqual(code, 1)
        self.assertRegex(err.getvalue(), r"^lodge\.py: error: .*not a LODGE clone")


class OfficialPlan(unittest.TestCase):
    """scripts/bench-lodge times the official loop at the batch sizes infer_lodge.py:211-216 gives
    a song: Local windows = frames // 256 (the tail dropped), Global = ceil(Local / 4)."""

    def test_window_counts_of_the_official_loop(self):
        # (frames, Global, Local), counted by hand from infer_lodge.py:211-216.
        for frames, want in ((1201, (1, 4)), (2047, (2, 7)), (2048, (2, 8)), (2100, (2, 8)),
                             (5401, (6, 21)), (5376, (6, 21)), (4096, (4, 16))):
            self.assertEqual(L.official_windows(frames), want, frames)


if __name__ == "__main__":
    unittest.main()
