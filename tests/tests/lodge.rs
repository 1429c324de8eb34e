//! End-to-end: `choreod dance --model` a LODGE package (the tiny random-weight one): a short
//! song (one Global window on padded music, under the official code's 34.1 s minimum) and a
//! longer one (two Global windows, the second partial), the licence line, and the motion file's
//! raw features and SMPL-X joints. Build first: `cargo build --release -p choreod`.

use std::process::Command;

use choreod_tests::{fixtures, python_cmd, run, stderr, workspace_root};

/// The first `seconds` of a fixture song.
fn song(dir: &std::path::Path, name: &str, seconds: f64) -> std::path::PathBuf {
    let out = dir.join(format!("{seconds}s.wav"));
    let status = Command::new("sox")
        .arg(fixtures().join("audio").join(name))
        .arg(&out)
        .args(["trim", "0", &seconds.to_string()])
        .status()
        .expect("sox (installed by scripts/setup)");
    assert!(status.success(), "sox could not cut the fixture");
    out
}

#[test]
fn lodge_packages_dance_short_and_long_songs_with_their_licence_and_raw_features() {
    let d = tempfile::tempdir().unwrap();
    let model = workspace_root().join("models/packages/lodge-tiny-random");
    for (seconds, source) in [
        (20.0, "vibe_ace_22k_mono.ogg"),
        (45.0, "hungarian_dance_5_44k_stereo.ogg"),
    ] {
        let audio = song(d.path(), source, seconds);
        let out = d.path().join(format!("{seconds}.h5"));
        let result = run(&[
            "dance",
            audio.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--model",
            model.to_str().unwrap(),
            "--genre",
            "Popping",
        ]);
        let err = stderr(&result);
        assert!(result.status.success(), "{err}");
        let licence = "licence: choreod test fixture (random weights) (commercial use allowed, \
                       redistribution allowed)";
        assert_eq!(
            err.lines().filter(|l| l.starts_with("licence: ")).count(),
            1,
            "{err}"
        );
        assert!(err.lines().any(|l| l == licence), "{err}");
        // Every frame of the song is danced (30 fps; the official code drops the tail under
        // 256 frames and crashes under 1024); features raw with their 6D rows unit vectors
        // (the un-normalised output went through Gram-Schmidt), the joints SMPL-X FK of them:
        // the pelvis at transl + J0, the bone lengths those of the rest joints.
        let check = python_cmd()
            .arg("-c")
            .arg(
                r#"
import sys, tomllib, h5py, numpy as np
f = h5py.File(sys.argv[1], "r")
m = tomllib.load(open(sys.argv[2] + "/choreod-model.toml", "rb"))
feat = f["motion/features"]
x, j = feat[...], f["motion/joints"][...]
frames = int(round(float(sys.argv[3]) * 30))
assert abs(x.shape[0] - frames) <= 1 and x.shape[1] == 139, x.shape
assert j.shape == (x.shape[0], 22, 3), j.shape
assert feat.attrs["representation"] == "lodge-smplx139" and not feat.attrs["normalized"]
rows = x[:, 7:].reshape(-1, 22, 2, 3)
assert np.allclose(np.linalg.norm(rows, axis=-1), 1, atol=1e-5)
rest = np.array(m["motion"]["rest_joints"]).reshape(-1, 3)
assert np.allclose(j[:, 0], x[:, 4:7] + rest[0], atol=1e-5)
P = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]
bone = np.linalg.norm(j[:, 1:] - j[:, P[1:]], axis=-1)
want = np.linalg.norm(rest[1:22] - rest[P[1:]], axis=-1)
assert np.allclose(bone, want, atol=1e-4), np.abs(bone - want).max()
assert f["motion"].attrs["skeleton"] == "smplx22"
lic = f["provenance"].attrs["license"]
assert lic.startswith("licence: choreod test fixture"), lic
print("ok", x.shape)
"#,
            )
            .args([
                out.to_str().unwrap(),
                model.to_str().unwrap(),
                &seconds.to_string(),
            ])
            .output()
            .expect("run the venv python");
        assert!(
            check.status.success(),
            "{}{}",
            String::from_utf8_lossy(&check.stdout),
            String::from_utf8_lossy(&check.stderr)
        );
        // BVH with the network's own rotations (no IK): read back, its joints are the motion
        // file's to 1 mm (6-decimal Euler degrees and offsets; the FK's Rodrigues vs the 6D
        // matrices differ by float rounding).
        let bvh = d.path().join(format!("{seconds}.bvh"));
        let back = d.path().join(format!("{seconds}.npy"));
        for (from, to) in [(&out, &bvh), (&bvh, &back)] {
            let r = run(&[
                "convert",
                from.to_str().unwrap(),
                "-o",
                to.to_str().unwrap(),
            ]);
            assert!(r.status.success(), "{}", stderr(&r));
        }
        let compare = python_cmd()
            .arg("-c")
            .arg(
                r#"
import sys, h5py, numpy as np
j = h5py.File(sys.argv[1], "r")["motion/joints"][...]
b = np.load(sys.argv[2])
assert b.shape == j.shape, (b.shape, j.shape)
gap = np.abs(b - j).max()
assert gap < 1e-3, gap
print("bvh ok", gap)
"#,
            )
            .args([out.to_str().unwrap(), back.to_str().unwrap()])
            .output()
            .expect("run the venv python");
        assert!(
            compare.status.success(),
            "{}{}",
            String::from_utf8_lossy(&compare.stdout),
            String::from_utf8_lossy(&compare.stderr)
        );
    }
}
