//! End-to-end: `choreod convert` and `choreod render` on the shared motion fixtures.
//! Build first: `cargo build -p choreod` (the tests run the binary).

use std::path::Path;
use std::process::Command;

use choreod_tests::{fixtures, one_error_line, python_cmd, run, stderr, stdout, workspace_root};

fn aistpp() -> String {
    fixtures()
        .join("motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl")
        .display()
        .to_string()
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

/// Run a numpy/h5py snippet with `args` as sys.argv[1:]; it prints "ok" when satisfied.
fn py(script: &str, args: &[&str]) {
    let out = python_cmd()
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("run python");
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "ok",
        "python check failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

fn ok(args: &[&str]) -> String {
    let out = run(args);
    assert!(
        out.status.success(),
        "choreod {args:?} failed: {}",
        stderr(&out)
    );
    stdout(&out)
}

#[test]
fn aistpp_to_motion_file_npy_and_bvh_agree() {
    let d = tempfile::tempdir().unwrap();
    let (h5, npy, bvh, back) = (
        d.path().join("a.h5"),
        d.path().join("a.npy"),
        d.path().join("a.bvh"),
        d.path().join("b.npy"),
    );
    ok(&["convert", &aistpp(), "-o", &s(&h5)]);
    ok(&["convert", &aistpp(), "-o", &s(&npy)]);
    ok(&["convert", &s(&h5), "-o", &s(&bvh)]);
    ok(&["convert", &s(&bvh), "-o", &s(&back)]);
    // Straight from the pickle, the BVH keeps AIST++'s own rotations.
    let (rot_bvh, rot_npy) = (d.path().join("rot.bvh"), d.path().join("rot.npy"));
    ok(&["convert", &aistpp(), "-o", &s(&rot_bvh)]);
    ok(&["convert", &s(&rot_bvh), "-o", &s(&rot_npy)]);
    py(
        r#"
import sys, h5py, numpy as np
f = h5py.File(sys.argv[1], "r")
assert f.attrs["format"] == "choreod-motion" and int(f.attrs["format_version"]) == 2
j = f["motion/joints"][:]
assert j.shape == (720, 24, 3) and j.dtype == np.float32
assert f["motion"].attrs["skeleton"] == "smpl24" and float(f["motion"].attrs["fps"]) == 60.0
a = np.load(sys.argv[2]); b = np.load(sys.argv[3]); r = np.load(sys.argv[4])
assert r.shape == j.shape and np.abs(r - j).max() < 1e-4, np.abs(r - j).max()
assert np.array_equal(a, j)
# BVH text keeps 6 decimals; rotations recovered from positions reproduce them to 1e-4 m.
assert b.shape == j.shape and np.abs(b - j).max() < 1e-4, np.abs(b - j).max()
print("ok")
"#,
        &[&s(&h5), &s(&npy), &s(&back), &s(&rot_npy)],
    );
}

#[test]
fn humanml3d_features_and_back() {
    let d = tempfile::tempdir().unwrap();
    let (h5, feat, joints, feat2) = (
        d.path().join("a.h5"),
        d.path().join("f.npy"),
        d.path().join("j.npy"),
        d.path().join("f2.npy"),
    );
    ok(&["convert", &aistpp(), "-o", &s(&h5)]);
    let msg = ok(&["convert", &s(&h5), "-o", &s(&feat), "--to", "features"]);
    assert!(msg.contains("[239, 263]"), "{msg}");
    ok(&["convert", &s(&feat), "-o", &s(&joints)]);
    ok(&["convert", &s(&joints), "-o", &s(&feat2)]);
    py(
        r#"
import sys, numpy as np
f = np.load(sys.argv[1]); j = np.load(sys.argv[2]); f2 = np.load(sys.argv[3])
assert f.shape == (239, 263) and f.dtype == np.float32
assert j.shape == (239, 22, 3)
assert set(np.unique(f[:, 259:])) <= {0.0, 1.0}
assert f2.shape == (238, 263)
# Re-extracting from recovered joints keeps the root height and ric within 1 mm.
assert np.abs(f2[:, 3:67] - f[:-1, 3:67]).max() < 1e-3, np.abs(f2[:, 3:67] - f[:-1, 3:67]).max()
print("ok")
"#,
        &[&s(&feat), &s(&joints), &s(&feat2)],
    );
}

#[test]
fn render_gif_and_png() {
    let d = tempfile::tempdir().unwrap();
    let (h5, gif, png) = (
        d.path().join("a.h5"),
        d.path().join("a.gif"),
        d.path().join("a.png"),
    );
    ok(&["convert", &aistpp(), "-o", &s(&h5)]);
    ok(&["render", &s(&h5), "-o", &s(&gif)]);
    ok(&[
        "render",
        &s(&h5),
        "-o",
        &s(&png),
        "--width",
        "200",
        "--height",
        "200",
    ]);
    let g = std::fs::read(&gif).unwrap();
    assert!(g.starts_with(b"GIF89a"));
    let p = std::fs::read(&png).unwrap();
    assert!(p.starts_with(b"\x89PNG\r\n\x1a\n"));
    // IHDR: width and height of a 4×3 sheet of 200-px tiles.
    assert_eq!(u32::from_be_bytes([p[16], p[17], p[18], p[19]]), 800);
    assert_eq!(u32::from_be_bytes([p[20], p[21], p[22], p[23]]), 600);
    // CMU BVH renders too.
    let cmu = fixtures().join("motion/cmu_01_01.bvh");
    ok(&["render", &s(&cmu), "-o", &s(&d.path().join("cmu.png"))]);
}

#[test]
fn bad_motion_inputs_are_one_clear_line() {
    let d = tempfile::tempdir().unwrap();
    let out_h5 = s(&d.path().join("out.h5"));
    // Truncated pickle.
    let bytes = std::fs::read(aistpp()).unwrap();
    let trunc = d.path().join("trunc.pkl");
    std::fs::write(&trunc, &bytes[..bytes.len() / 2]).unwrap();
    let e = one_error_line(&run(&["convert", &s(&trunc), "-o", &out_h5]));
    assert!(e.contains("trunc.pkl") && e.contains("truncated"), "{e}");
    // A pickle that would run a command.
    let evil = d.path().join("evil.pkl");
    std::fs::write(&evil, b"\x80\x02cos\nsystem\nX\x02\x00\x00\x00id\x85R.").unwrap();
    let e = one_error_line(&run(&["convert", &s(&evil), "-o", &out_h5]));
    assert!(e.contains("evil.pkl") && e.contains("os.system"), "{e}");
    // A dict without the AIST++ keys.
    let nokeys = d.path().join("nokeys.pkl");
    std::fs::write(&nokeys, b"\x80\x04}\x94.").unwrap();
    let e = one_error_line(&run(&["convert", &s(&nokeys), "-o", &out_h5]));
    assert!(e.contains("missing key 'smpl_poses'"), "{e}");
    // A text file posing as a motion file.
    let fake = d.path().join("fake.h5");
    std::fs::write(&fake, "not hdf5").unwrap();
    let e = one_error_line(&run(&[
        "render",
        &s(&fake),
        "-o",
        &s(&d.path().join("x.gif")),
    ]));
    assert!(
        e.contains("fake.h5") && e.contains("not an HDF5 file"),
        "{e}"
    );
    // Unknown output type.
    let e = one_error_line(&run(&[
        "convert",
        &aistpp(),
        "-o",
        &s(&d.path().join("x.fbx")),
    ]));
    assert!(e.contains("x.fbx"), "{e}");
    assert!(!Path::new(&out_h5).exists());
}

/// Run `choreod` under an address-space limit of 4 GiB, as the hostile inputs were found.
fn run_limited(args: &[&str]) -> std::process::Output {
    Command::new("prlimit")
        .arg("--as=4294967296")
        .arg("--")
        .arg(choreod_tests::choreod_bin())
        .args(args)
        .env_remove("RUST_LOG")
        .output()
        .expect("run prlimit (util-linux)")
}

/// Joints of the AIST++ fixture as `.npy` (720 frames at 60 fps) in `dir`.
fn aistpp_npy(dir: &Path) -> String {
    let npy = s(&dir.join("aist.npy"));
    ok(&["convert", &aistpp(), "-o", &npy]);
    npy
}

#[test]
fn hdf5_links_and_external_storage_are_refused() {
    let d = tempfile::tempdir().unwrap();
    let base = d.path().join("base.h5");
    ok(&["convert", &aistpp(), "-o", &s(&base)]);
    // Copies of a real motion file whose /motion/joints leads outside the file.
    py(
        r#"
import sys, os, shutil, h5py, numpy as np
base, d = sys.argv[1], sys.argv[2]
secret = os.path.join(d, "secret.bin")
with open(secret, "wb") as f:
    f.write(np.full((1, 24, 3), 1234.5, np.float32).tobytes())
with h5py.File(os.path.join(d, "other.h5"), "w") as f:
    f["j"] = np.full((1, 24, 3), 1234.5, np.float32)
for name in ["storage", "extlink", "softlink", "virtual"]:
    p = os.path.join(d, name + ".h5")
    shutil.copy(base, p)
    with h5py.File(p, "a") as f:
        m = f["motion"]
        del m["joints"]
        if name == "storage":
            m.create_dataset("joints", shape=(1, 24, 3), dtype=np.float32, external=[(secret, 0, 288)])
        elif name == "extlink":
            m["joints"] = h5py.ExternalLink("other.h5", "/j")
        elif name == "softlink":
            f["elsewhere"] = np.zeros((1, 24, 3), np.float32)
            m["joints"] = h5py.SoftLink("/elsewhere")
        else:
            layout = h5py.VirtualLayout(shape=(1, 24, 3), dtype=np.float32)
            layout[:] = h5py.VirtualSource("other.h5", "j", shape=(1, 24, 3))
            m.create_virtual_dataset("joints", layout)
print("ok")
"#,
        &[&s(&base), &s(d.path())],
    );
    for (name, feature) in [
        ("storage", "external raw-data storage"),
        ("extlink", "an external or user-defined link"),
        ("softlink", "a soft link"),
        ("virtual", "a virtual dataset"),
    ] {
        let input = s(&d.path().join(format!("{name}.h5")));
        let out = d.path().join(format!("{name}.npy"));
        let e = one_error_line(&run(&["convert", &input, "-o", &s(&out)]));
        assert!(
            e.contains(&format!(
                "{name}.h5: '/motion/joints': {feature} is not accepted"
            )),
            "{e}"
        );
        assert!(!out.exists(), "{name}: output written");
        let e = one_error_line(&run(&["render", &input, "-o", &s(&d.path().join("x.gif"))]));
        assert!(e.contains(feature), "{e}");
    }
}

#[test]
fn tiny_files_cannot_inflate_memory() {
    let d = tempfile::tempdir().unwrap();
    let out = s(&d.path().join("out.npy"));
    // 41 KB of BVH declaring 1,024 joints × 10^6 frames (12 GB of positions).
    let mut bvh = String::from("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 0\n");
    for k in 1..1024 {
        bvh.push_str(&format!("JOINT j{k}\n{{\nOFFSET 0 1 0\nCHANNELS 0\n}}\n"));
    }
    bvh.push_str("}\nMOTION\nFrames: 1000000\nFrame Time: 0.01\n");
    let wide = d.path().join("wide.bvh");
    std::fs::write(&wide, &bvh).unwrap();
    // 8 MB pickle: one memoised buffer decoded 600 times (≈ 38 GB as f64).
    let n = 8 << 20;
    let mut pkl = b"\x80\x04}\x8c\x0asmpl_poses](".to_vec();
    for i in 0..600 {
        pkl.extend_from_slice(b"cnumpy.core.numeric\n_frombuffer\n(");
        if i == 0 {
            pkl.push(b'B');
            pkl.extend_from_slice(&(n as u32).to_le_bytes());
            pkl.extend(std::iter::repeat_n(1u8, n));
            pkl.push(0x94);
        } else {
            pkl.extend_from_slice(b"h\x00");
        }
        pkl.extend_from_slice(b"cnumpy\ndtype\n\x8c\x02u1\x85RJ");
        pkl.extend_from_slice(&(n as i32).to_le_bytes());
        pkl.extend_from_slice(b"\x85\x8c\x01CtR");
    }
    pkl.extend_from_slice(b"es.");
    let reuse = d.path().join("reuse.pkl");
    std::fs::write(&reuse, &pkl).unwrap();
    // Motion files whose joints (3.9 GB) are declared but never written, plain and gzip.
    let base = d.path().join("base.h5");
    ok(&["convert", &aistpp(), "-o", &s(&base)]);
    py(
        r#"
import sys, os, shutil, h5py, numpy as np
base, d = sys.argv[1], sys.argv[2]
for name, opts in [("unwritten", {}), ("unwritten_gzip", {"chunks": (64, 24, 3), "compression": "gzip"})]:
    p = os.path.join(d, name + ".h5")
    shutil.copy(base, p)
    with h5py.File(p, "a") as f:
        del f["motion/joints"]
        f["motion"].create_dataset("joints", shape=(13_500_000, 24, 3), dtype=np.float32, **opts)
    assert os.path.getsize(p) < 100_000, os.path.getsize(p)
print("ok")
"#,
        &[&s(&base), &s(d.path())],
    );
    for (input, want) in [
        (wide, "exceeds the limit"),
        (reuse, "buffers reused"),
        (d.path().join("unwritten.h5"), "exceeds the limit"),
        (d.path().join("unwritten_gzip.h5"), "exceeds the limit"),
    ] {
        let r = run_limited(&["convert", &s(&input), "-o", &out]);
        assert_eq!(
            r.status.code(),
            Some(1),
            "{}: {}",
            input.display(),
            stderr(&r)
        );
        let e = one_error_line(&r);
        assert!(e.contains(&s(&input)) && e.contains(want), "{e}");
    }
    // Under the cap, unwritten data is refused for what it is (not read as fill values).
    let e = one_error_line(&run_limited(&[
        "convert",
        &s(&d.path().join("unwritten_gzip.h5")),
        "-o",
        &out,
        "--max-elements",
        "1000000000",
    ]));
    assert!(e.contains("only 0 of its 210938 chunks written"), "{e}");
    assert!(!Path::new(&out).exists());
}

#[test]
fn render_finishes_on_far_or_huge_coordinates() {
    let d = tempfile::tempdir().unwrap();
    let npy = aistpp_npy(d.path());
    let (far, huge) = (d.path().join("far.npy"), d.path().join("huge.npy"));
    py(
        r#"
import sys, numpy as np
j = np.load(sys.argv[1])
far = j.copy(); far[..., 0] += 3.0e7
np.save(sys.argv[2], far)
huge = j.copy(); huge[7, 3, 2] = 1.0e30
np.save(sys.argv[3], huge)
print("ok")
"#,
        &[&npy, &s(&far), &s(&huge)],
    );
    // 30 km from the origin the old `x += 0.5` grid loop never ended.
    let mut child = choreod_tests::choreod()
        .args(["render", &s(&far), "-o", &s(&d.path().join("far.png"))])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let start = std::time::Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        // Drawing 720 small frames takes well under a second; 30 s is a hang.
        if start.elapsed() > std::time::Duration::from_secs(30) {
            child.kill().unwrap();
            panic!("render of far-away motion did not finish in 30 s");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    assert!(status.success());
    let e = one_error_line(&run(&[
        "render",
        &s(&huge),
        "-o",
        &s(&d.path().join("huge.gif")),
    ]));
    assert!(e.contains("holds 1e30 at index 515, beyond ±1e8"), "{e}");
}

#[test]
fn every_verb_refuses_non_finite_and_empty_motion() {
    let d = tempfile::tempdir().unwrap();
    let (nan, inf, empty) = (
        d.path().join("nan.npy"),
        d.path().join("inf.npy"),
        d.path().join("empty.npy"),
    );
    py(
        r#"
import sys, numpy as np
j = np.zeros((10, 22, 3), np.float32); j[4, 5, 1] = np.nan
np.save(sys.argv[1], j)
j[4, 5, 1] = np.inf
np.save(sys.argv[2], j)
np.save(sys.argv[3], np.zeros((0, 22, 3), np.float32))
print("ok")
"#,
        &[&s(&nan), &s(&inf), &s(&empty)],
    );
    for (input, want) in [
        (
            &nan,
            "joint positions holds a non-finite value (NaN or infinity) at index 280",
        ),
        (
            &inf,
            "joint positions holds a non-finite value (NaN or infinity) at index 280",
        ),
        (&empty, "the motion has no frames"),
    ] {
        // One rule, one message, whatever the verb or the output.
        for out in ["out.h5", "out.npy", "out.bvh", "out.gif", "out.png"] {
            let out = d.path().join(out);
            let verb = if s(&out).ends_with(".gif") || s(&out).ends_with(".png") {
                "render"
            } else {
                "convert"
            };
            let r = run(&[verb, &s(input), "-o", &s(&out)]);
            assert_eq!(r.status.code(), Some(1));
            let e = one_error_line(&r);
            assert!(e.contains(&format!("{}: {want}", s(input))), "{verb}: {e}");
            assert!(!out.exists());
        }
    }
}

#[test]
fn frame_rates_survive_npy_and_bvh() {
    let d = tempfile::tempdir().unwrap();
    let npy = aistpp_npy(d.path());
    // Without --fps a .npy's rate is assumed, and said.
    let r = run(&["convert", &npy, "-o", &s(&d.path().join("assumed.h5"))]);
    assert!(r.status.success(), "{}", stderr(&r));
    assert!(
        stdout(&r).contains("at 30 fps (input frame rate assumed: pass --fps)"),
        "{}",
        stdout(&r)
    );
    assert!(stderr(&r).contains("frame rate assumed"), "{}", stderr(&r));
    // With --fps the 60 fps take stays 60 fps through .npy → .bvh → .h5, exactly.
    let (bvh, h5) = (d.path().join("a.bvh"), d.path().join("a.h5"));
    let msg = ok(&["convert", &npy, "--fps", "60", "-o", &s(&bvh)]);
    assert!(
        msg.contains("at 60 fps") && !msg.contains("assumed"),
        "{msg}"
    );
    ok(&["convert", &s(&bvh), "-o", &s(&h5)]);
    py(
        r#"
import sys, h5py
assert float(h5py.File(sys.argv[1], "r")["motion"].attrs["fps"]) == 60.0
print("ok")
"#,
        &[&s(&h5)],
    );
    // --fps is for .npy only: other inputs record their rate.
    let e = one_error_line(&run(&[
        "convert",
        &s(&bvh),
        "--fps",
        "30",
        "-o",
        &s(&d.path().join("x.h5")),
    ]));
    // The library names no flag; the binary appends the one the user can change.
    assert!(
        e.contains("applies to .npy input only (a BVH records its own) (--fps)"),
        "{e}"
    );
}

#[test]
fn converted_motion_files_record_their_source() {
    let d = tempfile::tempdir().unwrap();
    let h5 = d.path().join("a.h5");
    ok(&["convert", &aistpp(), "--to", "features", "-o", &s(&h5)]);
    py(
        r#"
import sys, os, hashlib, h5py
p = h5py.File(sys.argv[1], "r")["provenance"].attrs
src = sys.argv[2]
assert p["source_name"] == os.path.basename(src), p["source_name"]
assert p["source_sha256"] == hashlib.sha256(open(src, "rb").read()).hexdigest()
assert p["model_name"] == "choreod convert", p["model_name"]
assert p["sampler"] == "AIST++ motion → motion file (choreod convert --to features)", p["sampler"]
assert p["started_utc"].endswith("Z") and p["finished_utc"] >= p["started_utc"]
print("ok")
"#,
        &[&s(&h5), &aistpp()],
    );
}

/// The CMU fixture's joint names as Mixamo names them (`mixamorig:` prefix): Mixamo's spine
/// is three joints above the hips (CMU's LowerBack, Spine, Spine1) and a neck; CMU's extra
/// joints keep their names behind the prefix.
fn mixamo_named(cmu_bvh: &str) -> String {
    let rename = |name: &str| -> String {
        let mixamo = match name {
            "LowerBack" => "Spine",
            "Spine" => "Spine1",
            "Spine1" => "Spine2",
            other => other,
        };
        format!("mixamorig:{mixamo}")
    };
    cmu_bvh
        .lines()
        .map(|line| {
            let trimmed = line.trim_start();
            let indent = &line[..line.len() - trimmed.len()];
            match trimmed.split_once(' ') {
                Some((kw @ ("ROOT" | "JOINT"), name)) => {
                    format!("{indent}{kw} {}", rename(name.trim()))
                }
                _ => line.to_string(),
            }
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// Issue 21: every motion file `stylize` accepts, `convert --to features`, `eval` (as a
/// generated motion, `--content` and `--reference`) and `render` accept too — one rig mapping
/// for every verb. A CMU BVH and the same capture with Mixamo's joint names: both are placed
/// on t2m-22 by name, and the hips and legs they share land on the same t2m joints, so the
/// root trajectory (TSI) and root height agree exactly between the two.
#[test]
fn every_verb_accepts_the_bvh_rigs_stylize_accepts() {
    let d = tempfile::tempdir().unwrap();
    let cmu = fixtures().join("motion/cmu_01_01.bvh");
    let mixamo = d.path().join("mixamo_01_01.bvh");
    let text = std::fs::read_to_string(&cmu).unwrap();
    std::fs::write(&mixamo, mixamo_named(&text)).unwrap();
    assert!(
        std::fs::read_to_string(&mixamo)
            .unwrap()
            .contains("JOINT mixamorig:Spine2")
    );
    for (name, bvh) in [("cmu", &cmu), ("mixamo", &mixamo)] {
        let bvh = s(bvh);
        let out = |ext: &str| s(&d.path().join(format!("{name}.{ext}")));
        ok(&[
            "stylize",
            "--model",
            &s(&workspace_root().join("models/packages/style-gaussian")),
            "--content",
            &bvh,
            "--style",
            &aistpp(),
            "-o",
            &out("styled.h5"),
        ]);
        ok(&[
            "convert",
            &bvh,
            "--to",
            "features",
            "-o",
            &out("features.npy"),
        ]);
        ok(&["render", &bvh, "-o", &out("gif")]);
        let eval = ok(&[
            "eval",
            &bvh,
            "--content",
            &bvh,
            "--reference",
            &bvh,
            "--json",
        ]);
        let report: serde_json::Value = serde_json::from_str(&eval).unwrap();
        let file = &report["generated"][0];
        // 2752 frames at 120 fps, its own trajectory as content: TSI exactly 0.
        assert_eq!(file["frames"], 2752, "{eval}");
        assert_eq!(file["tsi_m"], 0.0, "{eval}");
        assert_eq!(report["reference_count"], 1, "{eval}");
    }
    // The Mixamo capture scored against the CMU one as content: the same root path.
    let eval = ok(&["eval", &s(&mixamo), "--content", &s(&cmu), "--json"]);
    let report: serde_json::Value = serde_json::from_str(&eval).unwrap();
    assert_eq!(report["generated"][0]["tsi_m"], 0.0, "{eval}");
    py(
        r#"
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
"#,
        &[
            &s(&d.path().join("cmu.features.npy")),
            &s(&d.path().join("mixamo.features.npy")),
        ],
    );
}
