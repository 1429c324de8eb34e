//! Motion files in and out: `choreod convert` and `choreod render` on the shared fixtures, every
//! format's round trip, frame rates, provenance, the BVH rigs every verb accepts, and hostile
//! files (HDF5 links, chunks that crash or bomb libhdf5, a crashing HDF5 reader, tiny files that
//! ask for huge arrays, huge or non-finite values): one error line each, nothing allocated
//! beyond what the file holds.
//! Build first: `cargo build --release -p choreod` (the tests run the binary).

use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

use choreod_tests::{
    AISTPP_PKL as PKL, CRASHED, aistpp, choreod, cmu_bvh, crashing_h5_files as make_files,
    fails_with, fixtures, motion_asset as asset, motion_file, ok, one_error_line, package,
    path_arg as s, py, python_cmd, run, run_capped, stderr, stdout, text, usage_error,
    workspace_root,
};

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
        "formats/aistpp_to_motion_file_npy_and_bvh_agree",
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
        "formats/humanml3d_features_and_back",
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
        "formats/hdf5_links_and_external_storage_are_refused",
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
        "formats/tiny_files_cannot_inflate_memory",
        &[&s(&base), &s(d.path())],
    );
    for (input, want) in [
        (wide, "exceeds the limit"),
        (reuse, "buffers reused"),
        (d.path().join("unwritten.h5"), "exceeds the limit"),
        (d.path().join("unwritten_gzip.h5"), "exceeds the limit"),
    ] {
        let r = run_capped(&["convert", &s(&input), "-o", &out]);
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
    let e = one_error_line(&run_capped(&[
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
        "formats/render_finishes_on_far_or_huge_coordinates",
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
        "formats/every_verb_refuses_non_finite_and_empty_motion",
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
    py("formats/frame_rates_survive_npy_and_bvh", &[&s(&h5)]);
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
        "formats/converted_motion_files_record_their_source",
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
        "formats/every_verb_accepts_the_bvh_rigs_stylize_accepts",
        &[
            &s(&d.path().join("cmu.features.npy")),
            &s(&d.path().join("mixamo.features.npy")),
        ],
    );
}

/// Run a verb with a bound: `view` serves until stopped when it can read its file.
fn run_bounded(args: &[&str]) -> Output {
    let mut child = choreod()
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn choreod");
    let t0 = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if t0.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().expect("output")
}

#[test]
fn every_verb_that_reads_h5_says_one_line_when_the_reader_crashes() {
    let dir = tempfile::tempdir().expect("temp dir");
    let [good, flip, short] = make_files(dir.path());
    let out_npy = dir.path().join("o.npy");
    let out_png = dir.path().join("o.png");
    let out_h5 = dir.path().join("o.h5");
    let pkl = asset(PKL);
    for hostile in [&flip, &short] {
        let h = text(hostile);
        let verbs: [Vec<&str>; 5] = [
            vec!["convert", h, "-o", text(&out_npy)],
            vec!["render", h, "-o", text(&out_png)],
            vec![
                "stylize",
                "--content",
                h,
                "--style",
                text(&pkl),
                "-o",
                text(&out_h5),
            ],
            vec!["eval", h],
            vec!["view", h, "--bind", "127.0.0.1:0"],
        ];
        for args in verbs {
            let out = run_bounded(&args);
            // Before: exit 139 (SIGSEGV) and no line at all.
            assert_eq!(out.status.code(), Some(1), "{args:?}: {out:?}");
            let line = one_error_line(&out);
            assert!(
                line.starts_with(&format!("choreod: error: {h}: ")),
                "{args:?}: {line}"
            );
            // The bit flip gets past any check before reading: only the child's death says it.
            if hostile == &flip {
                assert!(line.ends_with(CRASHED), "{args:?}: {line}");
            }
        }
    }
    // The same reader reads a good file whole: what choreod wrote comes back through the child.
    let out = run(&["convert", text(&good), "-o", text(&out_npy)]);
    assert!(out.status.success(), "{out:?}");
    let joints = choreo_datasets::read_npy(&out_npy).expect("npy");
    let m = choreo_datasets::read_motion_file(&good).expect("read in-process");
    assert_eq!(joints.shape(), m.joints.shape());
    assert_eq!(
        joints.iter().copied().collect::<Vec<f32>>(),
        m.joints.iter().copied().collect::<Vec<f32>>()
    );
}

#[test]
fn frame_rates_outside_1_to_1000_fps_are_refused_before_resampling() {
    let d = tempfile::tempdir().unwrap();
    // The CMU BVH with one line edited: a 1000 s Frame Time made stylize resample 2752 frames
    // at 0.001 fps to 20 fps (55 million frames) and abort.
    let slow = d.path().join("slow.bvh");
    std::fs::write(
        &slow,
        cmu_bvh().replace("Frame Time: .0083333", "Frame Time: 1000"),
    )
    .unwrap();
    let out = run_capped(&[
        "stylize",
        "--content",
        &s(&slow),
        "--style",
        &aistpp(),
        "-o",
        &s(&d.path().join("styled.h5")),
        "--model",
        &package("style-gaussian"),
    ]);
    fails_with(
        &out,
        1,
        &[
            "slow.bvh: line 187: Frame Time '1000'",
            "outside the accepted 1..=1000 fps",
        ],
    );

    // An .h5 whose /motion fps is 1e-4 made convert --to features allocate 41 GB and abort.
    let h5 = motion_file(d.path());
    py(
        "formats/frame_rates_outside_1_to_1000_fps_are_refused_before_resampling",
        &[&s(&h5)],
    );
    let features = d.path().join("f.npy");
    let out = run_capped(&["convert", &s(&h5), "-o", &s(&features), "--to", "features"]);
    fails_with(&out, 1, &["ok.h5: /motion fps: 0.0001 fps is outside"]);
    let out = run_capped(&["eval", &s(&h5)]);
    fails_with(&out, 1, &["ok.h5: /motion fps"]);
    assert!(!features.exists());

    // Within the range, the resampled size is checked against the element cap before it is
    // allocated: 720 frames at 1 fps are 14,381 frames at 20 fps.
    let joints = d.path().join("j.npy");
    assert!(
        run(&["convert", &aistpp(), "-o", &s(&joints)])
            .status
            .success()
    );
    let out = run_capped(&[
        "convert",
        &s(&joints),
        "--fps",
        "1",
        "--to",
        "features",
        "-o",
        &s(&features),
        "--max-elements",
        "200000",
    ]);
    fails_with(
        &out,
        1,
        &[
            "resampling 720 frames from 1 fps to 20 fps would make 14381 frames of 66 values, over the limit of 200000 values (--max-elements)",
        ],
    );

    // Flags are checked by the parser.
    let npy = s(&joints);
    usage_error(
        &["convert", &npy, "-o", "x.h5", "--fps", "0.0001"],
        "--fps",
        "1..=1000",
    );
    usage_error(
        &["render", &npy, "-o", "x.gif", "--fps", "nan"],
        "--fps",
        "1..=1000",
    );
    usage_error(&["eval", &npy, "--bas-fps", "1e9"], "--bas-fps", "1..=1000");
    usage_error(
        &[
            "stylize",
            "--content",
            &npy,
            "--style",
            &npy,
            "-o",
            "x.h5",
            "--style-fps",
            "0",
        ],
        "--style-fps",
        "1..=1000",
    );
}

#[test]
fn hdf5_chunks_that_crash_or_bomb_libhdf5_are_refused_before_it_reads_them() {
    let d = tempfile::tempdir().unwrap();
    motion_file(d.path());
    py("formats/hdf5_variants", &[&s(d.path())]);
    for (name, want) in [
        (
            "short_chunk",
            "'/motion/joints': the chunk at [0, 0, 0] holding 10 bytes of its 207360 is not accepted",
        ),
        (
            "bomb",
            "'/motion/joints': the chunk at [0, 0, 0] inflating to more than its 207360 bytes is not accepted",
        ),
        (
            "huge_chunk",
            "'/motion/joints': chunks of [4000000, 24, 3] for data of [720, 24, 3]",
        ),
        ("unknown_filter", "'/motion/joints': the HDF5 filter 32123"),
    ] {
        let input = s(&d.path().join(format!("{name}.h5")));
        let out = d.path().join(format!("{name}.npy"));
        fails_with(
            &run_capped(&["convert", &input, "-o", &s(&out)]),
            1,
            &[&format!("{name}.h5: {want}")],
        );
        assert!(!out.exists(), "{name}");
        let gif = s(&d.path().join(format!("{name}.gif")));
        fails_with(&run_capped(&["render", &input, "-o", &gif]), 1, &[want]);
    }
    let out = run_capped(&[
        "convert",
        &s(&d.path().join("gzip_ok.h5")),
        "-o",
        &s(&d.path().join("gzip_ok.npy")),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
}

#[test]
fn huge_but_finite_motion_values_are_input_errors() {
    let d = tempfile::tempdir().unwrap();
    let text = cmu_bvh();
    // Root x of one frame set to 3e38: finite, and far beyond any motion in metres.
    let frame = text
        .lines()
        .skip_while(|l| !l.starts_with("Frame Time"))
        .nth(11)
        .unwrap();
    let (_, rest) = frame.split_once(' ').unwrap();
    let bvh = d.path().join("huge.bvh");
    std::fs::write(&bvh, text.replacen(frame, &format!("3e38 {rest}"), 1)).unwrap();
    let out = run(&["convert", &s(&bvh), "-o", &s(&d.path().join("x.h5"))]);
    fails_with(&out, 1, &["huge.bvh: joint positions holds", "beyond ±1e8"]);
    let out = run(&[
        "stylize",
        "--content",
        &s(&bvh),
        "--style",
        &aistpp(),
        "-o",
        &s(&d.path().join("styled.h5")),
        "--model",
        &package("style-gaussian"),
    ]);
    fails_with(&out, 1, &["huge.bvh", "beyond ±1e8"]);
}

/// Whether an strace line is libhdf5 opening `file`: its `open` has no `O_CLOEXEC` (choreod's
/// own opens, Rust's `File::open`, always set it; see `NO_HDF5_LOCKS` in the harness).
fn hdf5_open_of(line: &str, file: &str) -> bool {
    line.contains(&format!("\"{file}\"")) && line.contains("openat(") && !line.contains("O_CLOEXEC")
}

/// `dir/shard.h5`: a prep shard of one 2 s AIST++ sequence with music `beats` (frames at
/// 30 fps, any values: `tests/tools/hostile_h5.py shard`).
fn shard_with_beats(dir: &Path, beats: &[&str]) -> PathBuf {
    let shard = dir.join("shard.h5");
    let out = python_cmd()
        .arg(workspace_root().join("tests/tools/hostile_h5.py"))
        .args(["shard", text(&shard)])
        .args(beats)
        .output()
        .expect("python");
    assert!(out.status.success(), "{out:?}");
    shard
}

#[test]
fn eval_reads_a_prep_shard_only_in_reader_children() {
    let dir = tempfile::tempdir().expect("temp dir");
    let shard = shard_with_beats(dir.path(), &["10", "25", "40", "55"]);
    let trace = dir.path().join("strace.txt");
    let out = std::process::Command::new("strace")
        .args(["-f", "-qq", "-e", "trace=openat", "-o", text(&trace)])
        .arg(choreod_tests::choreod_bin())
        .args(["eval", text(&shard)])
        .env("HDF5_USE_FILE_LOCKING", "FALSE")
        .output()
        .expect("strace (scripts/setup installs it)");
    assert!(out.status.success(), "{out:?}");
    // The shard's sequence was read and evaluated.
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(
        report.contains("shard.h5:gBR_sBM_cAll_d04_mBR0_ch01: 120 frames at 60 fps"),
        "{report}"
    );
    // Its music beats came back from the child too: a BAS against them, not "no music beats".
    let bas = report
        .split("bas_music_beats ")
        .nth(1)
        .and_then(|rest| rest.split(',').next())
        .expect("a bas_music_beats");
    assert!(bas.parse::<f64>().is_ok_and(|b| b > 0.0), "{report}");
    // With -f every line starts with the pid; choreod's own is the first line's.
    let log = std::fs::read_to_string(&trace).expect("strace log");
    let main_pid = log
        .split_whitespace()
        .next()
        .expect("a traced call")
        .to_string();
    let hdf5_opens: Vec<&str> = log
        .lines()
        .filter(|l| hdf5_open_of(l, text(&shard)))
        .collect();
    // Format, sequence list, and the sequence: each in a child.
    assert!(hdf5_opens.len() >= 3, "{log}");
    assert!(
        hdf5_opens
            .iter()
            .all(|l| !l.starts_with(&format!("{main_pid} "))),
        "libhdf5 opened the shard in choreod itself: {hdf5_opens:?}"
    );
}

#[test]
fn eval_refuses_a_prep_shards_bad_beats_in_one_line() {
    let dir = tempfile::tempdir().expect("temp dir");
    let too_many: Vec<String> = (0..121).map(|_| "0".to_string()).collect();
    let too_many: Vec<&str> = too_many.iter().map(String::as_str).collect();
    let cases: [(&[&str], &str); 4] = [
        (&["-5", "10"], "beat 0 at -0.1666"),
        (&["40", "10"], "beat 1 at 0.333"),
        (
            &["10", "2147483647"],
            "is after the end (the sequence is 2.000 s)",
        ),
        (&too_many, "shape [121], expected (B ≤ 120)"),
    ];
    for (beats, want) in cases {
        let shard = shard_with_beats(dir.path(), beats);
        let out = run(&["eval", text(&shard)]);
        fails_with(
            &out,
            1,
            &[
                "shard.h5: sequence 'gBR_sBM_cAll_d04_mBR0_ch01': beats: ",
                want,
            ],
        );
    }
}

/// A BVH of the shared dance capture (`../shared/data/dance-mocap/FOLDER/NAME.bvh.gz`)
/// gunzipped into `dir`.
fn dance_mocap_bvh(dir: &Path, folder: &str, name: &str) -> PathBuf {
    let gz = fixtures()
        .join("../data/dance-mocap")
        .join(folder)
        .join(format!("{name}.bvh.gz"));
    let out = std::process::Command::new("gzip")
        .arg("-dc")
        .arg(&gz)
        .output()
        .expect("gzip runs");
    assert!(out.status.success(), "gzip -dc {}", gz.display());
    let bvh = dir.join(format!("{name}.bvh"));
    std::fs::write(&bvh, out.stdout).expect("BVH written");
    bvh
}

/// A BVH, the rig choreod should name, (t2m joint index, its source joint or the two of a
/// midpoint) to check, and the joint the left hand points to.
type RigCase = (
    PathBuf,
    &'static str,
    Vec<(usize, &'static str, &'static str)>,
    &'static str,
);

/// Issue 24: `convert --to smpl24` places a BVH of each rig of the dance library on SMPL-24 by
/// its joint names, End Sites included. The expected positions are computed here from the
/// BVH's own named joints (choreod's reader, checked against Blender elsewhere), by the names
/// each rig is documented with: t2m joints on named joints or midpoints, each hand at SMPL's
/// rest wrist-to-hand length (|SMPL24_OFFSETS[22]| = 8.8 cm) towards the rig's hand joint.
/// Tolerance 1e-5 m: the .npy is float32 of coordinates up to ~3 m (ulp 2.4e-7).
#[test]
fn convert_to_smpl24_places_every_dance_library_rig() {
    use choreo_datasets::read_bvh;
    use choreo_datasets::skeleton::SMPL24_OFFSETS;
    let d = tempfile::tempdir().unwrap();
    let cases: [RigCase; 5] = [
        (
            fixtures().join("motion/cmu_01_01.bvh"),
            "CMU rig",
            vec![
                (0, "Hips", "Hips"),
                (13, "LeftShoulder", "LeftArm"),
                (15, "Head", "Head"),
            ],
            "LFingers",
        ),
        (
            dance_mocap_bvh(d.path(), "cmu-55-dance", "55_01"),
            "CMU MotionBuilder rig",
            vec![
                (6, "Spine", "Spine1"),
                (10, "LeftToeBase", "LeftToeBase"),
                (20, "LeftHand", "LeftHand"),
            ],
            "LeftHandIndex1",
        ),
        (
            dance_mocap_bvh(d.path(), "cmu-60-61-salsa", "60_10_scaled"),
            "Poser rig",
            vec![
                (1, "lThigh", "lThigh"),
                (10, "lFoot_end", "lFoot_end"),
                (11, "rFoot_end", "rFoot_end"),
            ],
            "lMid1",
        ),
        (
            dance_mocap_bvh(d.path(), "cmu-85-breakdance", "85_03"),
            "Neo rig",
            vec![
                (9, "Neo_Spine2", "Neo_Spine2"),
                (18, "Neo_LeftForeArm", "Neo_LeftForeArm"),
            ],
            "Neo_LeftHand_end",
        ),
        (
            dance_mocap_bvh(d.path(), "cmu-05-modern", "005_03"),
            "Reallusion CC_Base rig",
            vec![
                (12, "CC_Base_NeckTwist01", "CC_Base_NeckTwist01"),
                (7, "CC_Base_L_Foot", "CC_Base_L_Foot"),
            ],
            "CC_Base_L_Mid1",
        ),
    ];
    for (bvh, rig, joints, hand) in cases {
        let npy = d.path().join("smpl24.npy");
        let said = ok(&["convert", &s(&bvh), "--to", "smpl24", "-o", &s(&npy)]);
        assert!(said.contains(rig) && said.contains("on SMPL-24"), "{said}");
        let got = choreo_datasets::read_npy(&npy).unwrap();
        let src = read_bvh(&bvh).unwrap();
        let frames = src.joints.shape()[0];
        assert_eq!(got.shape(), [frames, 24, 3], "{said}");
        let at = |name: &str, t: usize| -> [f32; 3] {
            let j = src.names.iter().position(|n| n == name).unwrap();
            [0, 1, 2].map(|c| src.joints[[t, j, c]])
        };
        let near = |a: [f32; 3], b: [f32; 3]| (0..3).all(|c| (a[c] - b[c]).abs() < 1e-5);
        let hand_len = SMPL24_OFFSETS[22].iter().map(|v| v * v).sum::<f32>().sqrt();
        for t in [0, frames / 2, frames - 1] {
            let g = |k: usize| [0, 1, 2].map(|c| got[[t, k, c]]);
            for &(k, a, b) in &joints {
                let want = [0, 1, 2].map(|c| 0.5 * (at(a, t)[c] + at(b, t)[c]));
                assert!(
                    near(g(k), want),
                    "{rig} joint {k} frame {t}: {:?} vs {want:?}",
                    g(k)
                );
            }
            let (wrist, towards) = (g(20), at(hand, t));
            let dir: Vec<f32> = (0..3).map(|c| towards[c] - wrist[c]).collect();
            let n = dir.iter().map(|v| v * v).sum::<f32>().sqrt();
            let want = [0, 1, 2].map(|c| wrist[c] + dir[c] * hand_len / n);
            assert!(
                near(g(22), want),
                "{rig} left hand frame {t}: {:?} vs {want:?}",
                g(22)
            );
        }
    }
    // t2m-22 has no hands: one clear line, not a guess.
    let t2m = d.path().join("t2m.npy");
    let cmu = fixtures().join("motion/cmu_01_01.bvh");
    ok(&[
        "convert",
        &s(&cmu),
        "--to",
        "features",
        "-o",
        &s(&d.path().join("f.npy")),
    ]);
    ok(&["convert", &s(&d.path().join("f.npy")), "-o", &s(&t2m)]);
    let out = run(&[
        "convert",
        &s(&t2m),
        "--to",
        "smpl24",
        "-o",
        &s(&d.path().join("x.npy")),
    ]);
    let line = one_error_line(&out);
    assert!(line.contains("t2m-22 joints have no hands"), "{line}");
}
