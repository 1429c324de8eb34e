//! End-to-end: `choreod dance --model` a LODGE package (the tiny random-weight one): a short
//! song (one Global window on padded music, under the official code's 34.1 s minimum) and a
//! longer one (two Global windows, the second partial), the licence line, and the motion file's
//! raw features and SMPL-X joints. Build first: `cargo build --release -p choreod`.

use std::process::Command;

use choreod_tests::daemon::{Home, PATIENCE};
use choreod_tests::{fixtures, package, python_cmd, run, stderr, text, workspace_root};

/// Run a Python check (the venv's: numpy, h5py) with `args`; it must exit 0.
fn python_check(code: &str, args: &[&str]) {
    let out = python_cmd()
        .arg("-c")
        .arg(code)
        .args(args)
        .output()
        .expect("run the venv python");
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

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
        let windows = d.path().join(format!("{seconds}.npz"));
        let result = run(&[
            "dance",
            audio.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--model",
            model.to_str().unwrap(),
            "--genre",
            "Popping",
            "--save-windows",
            windows.to_str().unwrap(),
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
        python_check(
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
# --save-windows: both stages' windows and every Local window's in-painting (Local_Module.py:
# 206-226): contacts and rotations of the 4 end rows at each side, the keyframe chunks at rows
# 28 and 156 and their mirrors at 60 and 188; the root translation free (its values are kept
# as the official code keeps them, unused).
w = np.load(sys.argv[4])
L = w["local_windows"].shape[0]
assert w["global_windows"].shape[1:] == (104, 139) and w["local_windows"].shape == (L, 256, 139)
value, mask = w["local_constraint_value"], w["local_constraint_mask"]
assert value.shape == mask.shape == (L, 256, 139) and L * 256 >= x.shape[0]
rows = np.r_[0:4, 28:36, 60:68, 156:164, 188:196, 252:256]
want = np.zeros((256, 139)); want[rows, :4] = 1; want[rows, 7:] = 1
assert (mask == want).all(), np.argwhere(mask != want)[:5]
free = np.setdiff1d(np.arange(256), rows)
assert (value[:, free] == 0).all() and np.abs(value[:, rows][:, :, 7:]).max() > 0.1
print("ok", x.shape)
"#,
            &[
                out.to_str().unwrap(),
                model.to_str().unwrap(),
                &seconds.to_string(),
                windows.to_str().unwrap(),
            ],
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
        python_check(
            r#"
import sys, h5py, numpy as np
j = h5py.File(sys.argv[1], "r")["motion/joints"][...]
b = np.load(sys.argv[2])
assert b.shape == j.shape, (b.shape, j.shape)
gap = np.abs(b - j).max()
assert gap < 1e-3, gap
print("bvh ok", gap)
"#,
            &[out.to_str().unwrap(), back.to_str().unwrap()],
        );
    }
    metrics_take_the_dance_on_smpl24(d.path(), &d.path().join("20.h5"));
}

/// A LODGE dance as the metrics see it: SMPL-24 joints whose first 22 are the motion file's
/// SMPL-X joints and whose hands (22, 23) are each wrist plus SMPL's rest wrist-to-hand bone
/// turned by the wrist's world rotation, recomputed here in numpy from the raw 6D features
/// (pytorch3d's `rotation_6d_to_matrix`: Gram-Schmidt rows); `eval` scores it on 24 joints
/// (72 kinetic features, 3 per joint; t2m-22 would give 66) and `convert --to features` takes it.
fn metrics_take_the_dance_on_smpl24(dir: &std::path::Path, h5: &std::path::Path) {
    let smpl = dir.join("smpl24.npy");
    let features = dir.join("features.npy");
    for (to, extra) in [(&smpl, None), (&features, Some("features"))] {
        let mut args = vec!["convert", text(h5), "-o", text(to)];
        if let Some(t) = extra {
            args.extend(["--to", t]);
        }
        let r = run(&args);
        assert!(r.status.success(), "{}", stderr(&r));
    }
    // Tolerance 1e-5 m: both sides compute in float64 from the same float32 features and
    // joints and round to float32 (joints of ~1 m: 1.2e-7 each).
    python_check(
        r#"
import sys, h5py, numpy as np
f = h5py.File(sys.argv[1], "r")
j, x = f["motion/joints"][...], f["motion/features"][...].astype(np.float64)
s = np.load(sys.argv[2])
assert s.shape == (j.shape[0], 24, 3), s.shape
assert np.array_equal(s[:, :22], j), "the first 22 joints are SMPL-X's, unchanged"
d6 = x[:, 7:].reshape(-1, 22, 6)
b1 = d6[..., :3] / np.linalg.norm(d6[..., :3], axis=-1, keepdims=True)
b2 = d6[..., 3:] - (b1 * d6[..., 3:]).sum(-1, keepdims=True) * b1
b2 /= np.linalg.norm(b2, axis=-1, keepdims=True)
R = np.stack([b1, b2, np.cross(b1, b2)], axis=-2)
# SMPL's rest wrist-to-hand offsets: Stanford-TML/EDGE vis.py smpl_offsets[22], [23].
off = {20: np.array([0.08669055, -0.01063603, -0.01559429]),
       21: np.array([-0.0887537, -0.00865157, -0.01010708])}
arms = {20: [0, 3, 6, 9, 13, 16, 18, 20], 21: [0, 3, 6, 9, 14, 17, 19, 21]}
for wrist, hand in [(20, 22), (21, 23)]:
    W = np.broadcast_to(np.eye(3), (len(x), 3, 3))
    for k in arms[wrist]:
        W = W @ R[:, k]
    want = j[:, wrist] + W @ off[wrist]
    gap = np.abs(s[:, hand] - want).max()
    assert gap < 1e-5, (hand, gap)
    moved = np.abs(s[:, hand] - (j[:, wrist] + off[wrist])).max()
    assert moved > 1e-2, ("the hand does not follow the wrist", moved)
h = np.load(sys.argv[3])
assert h.shape[1] == 263 and abs(h.shape[0] - len(j) * 20 / 30) <= 2, h.shape
print("smpl24 ok")
"#,
        &[text(h5), text(&smpl), text(&features)],
    );
    let scored = dir.join("scored");
    let eval = run(&["eval", text(h5), "--features-out", text(&scored)]);
    assert!(eval.status.success(), "{}", stderr(&eval));
    let kinetic = choreo_datasets::read_npy(&scored.join("00000_20.kinetic.npy")).expect("kinetic");
    assert_eq!(
        kinetic.shape(),
        [72],
        "3 kinetic features per SMPL-24 joint"
    );
}

/// A LODGE song cut short (the first 200 kB of a 1.45 MB OGG, a cut download: 5.6 s of 54 s,
/// as `serve_intake`'s log-mel test cuts it): `dance` makes the dance of what decodes and
/// records the damage in the provenance; `serve` with `limits.fail_truncated_audio = true`
/// refuses it at the decode stage, naming the key. Two steps: only the damage is under test.
#[test]
fn a_lodge_song_cut_short_records_its_damage_or_is_refused_when_configured() {
    let d = tempfile::tempdir().unwrap();
    let whole = std::fs::read(fixtures().join("audio/vibe_ace_44k_stereo.ogg")).expect("fixture");
    let cut = d.path().join("cut.ogg");
    std::fs::write(&cut, &whole[..200_000]).unwrap();
    let model = package("lodge-tiny-random");
    let out = d.path().join("cut.h5");
    let r = run(&[
        "dance",
        cut.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--model",
        &model,
        "--genre",
        "Popping",
        "--steps",
        "2",
    ]);
    assert!(r.status.success(), "{}", stderr(&r));
    let damage = choreo_datasets::read_motion_file(&out)
        .expect("a motion file")
        .provenance
        .expect("provenance")
        .source_damage
        .unwrap_or_default();
    assert!(
        damage.starts_with("the file ends mid-stream: "),
        "{damage:?}"
    );

    let mut home = Home::new(&format!(
        "[runtime]\ndefault_model = '{model}'\n\n[limits]\nmin_free_disk_mb = 1.0\n\
         fail_truncated_audio = true\n\n[serve]\nsettle_ms = 100\n\n[job]\nsteps = 2\n"
    ));
    std::fs::copy(&cut, home.inbox().join("cut.ogg")).unwrap();
    let mut daemon = home.start();
    home.wait_for_outcomes(1, &[], PATIENCE, &mut daemon);
    assert!(home.names("out").is_empty(), "{:?}", home.names("out"));
    let report = &home.reports()[0];
    let reason = report["reason"].as_str().unwrap_or_default();
    assert_eq!(report["stage"], "decode", "{report}");
    assert!(
        reason.contains("cut.ogg")
            && reason.contains("ends mid-stream")
            && reason.contains("limits.fail_truncated_audio"),
        "{reason}"
    );
}

/// `dance --features FILE.npy` (precomputed fact35 features, for checking against the official
/// code) names that file, its sha256 and what it is in the provenance: a reader must not take
/// it for the song.
#[test]
fn a_dance_of_precomputed_features_names_the_features_file_in_its_provenance() {
    let d = tempfile::tempdir().unwrap();
    let audio = song(d.path(), "vibe_ace_22k_mono.ogg", 5.0);
    let features = d.path().join("song.fact35.npy");
    let out = d.path().join("song.h5");
    for args in [
        vec![
            "features",
            audio.to_str().unwrap(),
            "-o",
            features.to_str().unwrap(),
            "--set",
            "fact35",
        ],
        vec![
            "dance",
            "--features",
            features.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--model",
            &package("lodge-tiny-random"),
            "--steps",
            "2",
        ],
    ] {
        let r = run(&args);
        assert!(r.status.success(), "{}", stderr(&r));
    }
    let p = choreo_datasets::read_motion_file(&out)
        .expect("a motion file")
        .provenance
        .expect("provenance");
    assert_eq!(p.source_name, "song.fact35.npy");
    assert_eq!(
        p.source_sha256,
        choreo_datasets::sha256_file(&features).unwrap()
    );
    assert_eq!(
        p.source_kind.as_deref(),
        Some("fact35 features (151, 35), danced instead of a song")
    );
}
