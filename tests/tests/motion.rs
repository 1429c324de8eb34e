//! End-to-end: `choreod convert` and `choreod render` on the shared motion fixtures.
//! Build first: `cargo build -p choreod` (the tests run the binary).

use std::path::Path;
use std::process::Command;

use choreod_tests::{fixtures, one_error_line, python, run, stderr, stdout};

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
    let out = Command::new(python())
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
assert f.attrs["format"] == "choreod-motion" and int(f.attrs["format_version"]) == 1
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
