//! End-to-end: inputs, flags and packages that used to abort, crash or mislead choreod (issue
//! 20) now get one error line and the documented exit code. Every hostile file is made here.
//! Build first: `cargo build --release -p choreod`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use choreod_tests::daemon::{Home, drop_file, wav_bytes};
use choreod_tests::{
    choreod, choreod_bin, fixtures, one_error_line, python_cmd, run, stderr, stdout, workspace_root,
};

fn s(p: &Path) -> String {
    p.display().to_string()
}

fn aistpp() -> String {
    s(&fixtures().join("motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"))
}

fn cmu_bvh() -> String {
    std::fs::read_to_string(fixtures().join("motion/cmu_01_01.bvh")).expect("CMU fixture")
}

fn package(name: &str) -> String {
    s(&workspace_root().join("models/packages").join(name))
}

/// Run choreod with at most 4 GiB of address space, so a build that tries to allocate what a
/// hostile file asks for fails there (exit 134) instead of driving the machine into swap.
fn run_capped(args: &[&str]) -> Output {
    Command::new("sh")
        .args(["-c", "ulimit -v 4194304 && exec \"$@\"", "sh"])
        .arg(choreod_bin())
        .args(args)
        .env_remove("RUST_LOG")
        .env("HDF5_USE_FILE_LOCKING", "FALSE")
        .output()
        .expect("spawn choreod")
}

/// Run a Python snippet with `args` as sys.argv[1:]; it prints "ok" when done.
fn py(script: &str, args: &[&str]) {
    let out = python_cmd()
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("run python");
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "ok",
        "python failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A failed run: exit `code` and one error line containing every one of `want`.
fn fails_with(out: &Output, code: i32, want: &[&str]) -> String {
    let line = one_error_line(out);
    assert_eq!(out.status.code(), Some(code), "{line}");
    for w in want {
        assert!(line.contains(w), "{w:?} not in: {line}");
    }
    line
}

/// A usage error printed by the parser (exit 2) naming `flag` and the accepted range.
fn usage_error(args: &[&str], flag: &str, range: &str) {
    let out = run(args);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(2), "choreod {args:?}: {err}");
    assert!(
        err.contains(flag) && err.contains(&format!("must be in {range}")),
        "choreod {args:?}: {err}"
    );
}

/// The AIST++ fixture as a motion file (720 frames at 60 fps) in `dir`.
fn motion_file(dir: &Path) -> PathBuf {
    let h5 = dir.join("ok.h5");
    let out = run(&["convert", &aistpp(), "-o", &s(&h5)]);
    assert!(out.status.success(), "{}", stderr(&out));
    h5
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
        "import sys, h5py, numpy as np\nwith h5py.File(sys.argv[1], 'r+') as f:\n    f['motion'].attrs['fps'] = np.float32(1e-4)\nprint('ok')",
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

/// A motion file made from `ok.h5` with `/motion/joints` (720, 24, 3) replaced by `make(g, j)`.
const HDF5_VARIANTS: &str = r#"
import sys, os, shutil, zlib, h5py, numpy as np
d = sys.argv[1]
def variant(name, make):
    dst = os.path.join(d, name)
    shutil.copy(os.path.join(d, "ok.h5"), dst)
    with h5py.File(dst, "r+") as f:
        j = f["motion/joints"][...]
        del f["motion/joints"]
        make(f["motion"], j)
def chunked(g, j, chunks=None, **kw):
    return g.create_dataset("joints", shape=j.shape, maxshape=(None, 24, 3), chunks=chunks or j.shape, dtype="f4", **kw)
# One unfiltered chunk stored as 10 bytes (nominal 207,360): libhdf5 1.10 read past it (SIGSEGV).
variant("short_chunk.h5", lambda g, j: chunked(g, j).id.write_direct_chunk((0, 0, 0), bytes(10)))
# One gzip chunk of 64 MB of zeros (nominal 207,360): libhdf5 inflates all of it.
variant("bomb.h5", lambda g, j: chunked(g, j, compression="gzip").id.write_direct_chunk((0, 0, 0), zlib.compress(bytes(64 << 20))))
# Chunks of (4,000,000, 24, 3) for 720 frames.
variant("huge_chunk.h5", lambda g, j: chunked(g, j, chunks=(4000000, 24, 3), compression="gzip").id.write_direct_chunk((0, 0, 0), zlib.compress(j.astype("<f4").tobytes())))
# A filter libhdf5 does not know (it searched its plugin directory for it).
def unknown_filter(g, j):
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk(j.shape)
    dcpl.set_filter(32123, h5py.h5z.FLAG_OPTIONAL, ())
    space = h5py.h5s.create_simple(j.shape, (h5py.h5s.UNLIMITED, 24, 3))
    x = h5py.h5d.create(g.id, b"joints", h5py.h5t.IEEE_F32LE, space, dcpl=dcpl)
    x.write_direct_chunk((0, 0, 0), j.astype("<f4").tobytes(), filter_mask=0)
variant("unknown_filter.h5", unknown_filter)
# What h5py users write: gzip + shuffle + Fletcher-32 in 64-frame chunks (the last one partial).
variant("gzip_ok.h5", lambda g, j: g.create_dataset("joints", data=j, maxshape=(None, 24, 3), chunks=(64, 24, 3), compression="gzip", shuffle=True, fletcher32=True))
print("ok")
"#;

#[test]
fn hdf5_chunks_that_crash_or_bomb_libhdf5_are_refused_before_it_reads_them() {
    let d = tempfile::tempdir().unwrap();
    motion_file(d.path());
    py(HDF5_VARIANTS, &[&s(d.path())]);
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
fn input_text_in_error_lines_is_cut_short() {
    let d = tempfile::tempdir().unwrap();
    let token = "A".repeat(10 << 20);
    let check = |out: &Output| {
        let line = one_error_line(out);
        assert!(line.len() < 400, "{} bytes: {}", line.len(), &line[..400]);
        assert!(line.contains(&format!("…' ({} bytes)", 10 << 20)), "{line}");
    };
    // A 10 MB token where the BVH's first keyword belongs.
    let bvh = d.path().join("token.bvh");
    std::fs::write(&bvh, cmu_bvh().replacen("HIERARCHY", &token, 1)).unwrap();
    check(&run(&[
        "convert",
        &s(&bvh),
        "-o",
        &s(&d.path().join("x.npy")),
    ]));
    // ... and as a beat time of `eval --beats`.
    let beats = d.path().join("beats.txt");
    std::fs::write(&beats, format!("0.5\n{token}\n")).unwrap();
    check(&run(&["eval", &aistpp(), "--beats", &s(&beats)]));
    // A .npy header holds at most 64 KiB: its dtype is cut as well.
    let npy = d.path().join("dtype.npy");
    py(
        "import sys\nh = \"{'descr': '\" + 'x' * 60000 + \"', 'fortran_order': False, 'shape': (1,), }\"\nh = h + ' ' * (63 - (len(h) + 10) % 64) + '\\n'\nopen(sys.argv[1], 'wb').write(b'\\x93NUMPY\\x01\\x00' + len(h).to_bytes(2, 'little') + h.encode())\nprint('ok')",
        &[&s(&npy)],
    );
    let line = one_error_line(&run(&[
        "convert",
        &s(&npy),
        "-o",
        &s(&d.path().join("y.h5")),
    ]));
    assert!(line.len() < 400 && line.contains("(60000 bytes)"), "{line}");
}

#[test]
fn megabyte_keys_and_values_in_a_config_or_manifest_give_a_short_line() {
    let d = tempfile::tempdir().unwrap();
    let big = "A".repeat(1 << 20);
    let short = |out: &Output, code: i32| {
        let line = one_error_line(out);
        assert_eq!(
            out.status.code(),
            Some(code),
            "{}",
            &line[..line.len().min(400)]
        );
        // A megabyte in, under a kilobyte out (the config's other problems included).
        assert!(line.len() < 1000, "{} bytes: {}", line.len(), &line[..1000]);
        // Cut, with the length (1 MiB and the few bytes of a key's table or a value's quotes).
        assert!(line.contains("…' (10485"), "{line}");
        line
    };
    // The config: a 1 MB unknown key (TOML's message quotes it, and the line names it), and a
    // 1 MB value of a known key.
    let config = d.path().join("choreod.toml");
    std::fs::write(&config, format!("[job]\n{big} = 1\n")).unwrap();
    let line = short(&run(&["check-config", &s(&config)]), 3);
    assert!(
        line.contains("line 2, key `'job.AAAA") && line.contains("unknown field `'AAAA"),
        "{line}"
    );
    std::fs::write(&config, format!("[log]\nlevel = \"{big}\"\n")).unwrap();
    let line = short(&run(&["check-config", &s(&config)]), 3);
    assert!(line.contains("invalid `log.level`"), "{line}");
    // A manifest: a 1 MB `format` value and a 1 MB unknown key.
    let pkg = edited_package(d.path(), "format", |t| {
        t.replacen(
            "format = \"choreod-model\"",
            &format!("format = \"{big}\""),
            1,
        )
    });
    let line = short(&run(&["models", "check", &pkg]), 4);
    assert!(
        line.contains("choreod-model.toml: format: is 'AAAA"),
        "{line}"
    );
    let pkg = edited_package(d.path(), "key", |t| {
        t.replacen("[motion]", &format!("{big} = 1\n\n[motion]"), 1)
    });
    let line = short(&run(&["models", "check", &pkg]), 4);
    assert!(line.contains("unknown field `'AAAA"), "{line}");
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

#[test]
fn out_of_range_flags_are_usage_errors() {
    // A missing song: the parser must refuse the flag before anything is read.
    let song = "missing.ogg";
    usage_error(
        &["dance", song, "-o", "x.h5", "--guidance", "1e30"],
        "--guidance",
        "0..=100",
    );
    usage_error(
        &["dance", song, "-o", "x.h5", "--eta", "1e300"],
        "--eta",
        "0..=1",
    );
    usage_error(
        &["dance", song, "-o", "x.h5", "--intra-threads", "100000"],
        "--intra-threads",
        "0..=",
    );
    usage_error(
        &["dance", song, "-o", "x.h5", "--max-duration", "nan"],
        "--max-duration",
        "0.1..=86400",
    );
    usage_error(
        &["mel", song, "-o", "x.npy", "--max-duration", "inf"],
        "--max-duration",
        "0.1..=86400",
    );
    let m = aistpp();
    usage_error(
        &[
            "stylize",
            "--content",
            &m,
            "--style",
            &m,
            "-o",
            "x.h5",
            "--guidance=-1",
        ],
        "--guidance",
        "0..=100",
    );
    usage_error(
        &[
            "stylize",
            "--content",
            &m,
            "--style",
            &m,
            "-o",
            "x.h5",
            "--mode",
            "inversion",
            "--style-guidance",
            "1e30",
        ],
        "--style-guidance",
        "0..=100",
    );
    usage_error(
        &[
            "stylize",
            "--content",
            &m,
            "--style",
            &m,
            "-o",
            "x.h5",
            "--intra-threads",
            "2000",
        ],
        "--intra-threads",
        "0..=",
    );
}

#[test]
fn an_output_that_is_an_input_is_refused_and_the_input_kept() {
    let d = tempfile::tempdir().unwrap();
    let h5 = motion_file(d.path());
    let before = std::fs::read(&h5).unwrap();
    let link = d.path().join("link.h5");
    std::os::unix::fs::symlink(&h5, &link).unwrap();
    let dotted = format!("{}/./ok.h5", d.path().display());
    for output in [s(&h5), dotted, s(&link)] {
        let out = run(&["convert", &s(&h5), "-o", &output]);
        fails_with(
            &out,
            2,
            &["is the same file as the input", "choose another output"],
        );
    }
    let out = run(&[
        "stylize",
        "--content",
        &aistpp(),
        "--style",
        &s(&h5),
        "-o",
        &s(&link),
        "--model",
        &package("style-gaussian"),
    ]);
    fails_with(&out, 2, &["-o", "is the same file as --style"]);
    assert_eq!(
        std::fs::read(&h5).unwrap(),
        before,
        "the input was replaced"
    );
}

/// `models/packages/exemplar` copied to `dir/name` with `edit` applied to its manifest.
fn edited_package(dir: &Path, name: &str, edit: impl Fn(String) -> String) -> String {
    let to = dir.join(name);
    std::fs::create_dir(&to).expect("package folder");
    let from = workspace_root().join("models/packages/exemplar");
    for entry in std::fs::read_dir(&from).expect("bundled exemplar") {
        let entry = entry.expect("bundled exemplar entry");
        std::fs::copy(entry.path(), to.join(entry.file_name())).expect("copy the package");
    }
    let manifest = to.join("choreod-model.toml");
    let text = std::fs::read_to_string(&manifest).expect("manifest");
    std::fs::write(&manifest, edit(text)).expect("write the manifest");
    s(&to)
}

#[test]
fn models_check_refuses_manifests_no_song_can_pass() {
    let d = tempfile::tempdir().unwrap();
    for (name, from, to, want) in [
        (
            "rate",
            "sample_rate = 16000",
            "sample_rate = 4000000000",
            "audio.sample_rate: 4000000000: must be in 1..=768000 Hz",
        ),
        (
            "fft",
            "n_fft = 2048",
            "n_fft = 2147483648",
            "audio.n_fft: 2147483648: must be in 16..=65536",
        ),
        (
            "fps",
            "fps = 30.0",
            "fps = 1e-300",
            "motion.fps: must be in 1..=1000 frames per second, got 1e-300",
        ),
        (
            "guidance",
            "guidance = 1.0",
            "guidance = 1e30",
            "sampler.guidance: must be in 0..=100",
        ),
    ] {
        let pkg = edited_package(d.path(), name, |t| t.replacen(from, to, 1));
        let out = run(&["models", "check", &pkg]);
        fails_with(
            &out,
            4,
            &[&format!("model package {pkg}: choreod-model.toml: {want}")],
        );
    }
}

#[test]
fn onnx_runtime_messages_do_not_precede_the_error_line() {
    let d = tempfile::tempdir().unwrap();
    // A denoiser that fails inside ONNX Runtime at run time (an index out of range), which
    // ONNX Runtime used to log itself, in colour, before choreod's line.
    let pkg = edited_package(d.path(), "broken", |t| t);
    let onnx = Path::new(&pkg).join("denoiser.onnx");
    py(
        r#"
import sys, hashlib, onnx
from onnx import helper, numpy_helper, TensorProto as T
import numpy as np
io = lambda n, t, s: helper.make_tensor_value_info(n, t, s)
g = helper.make_graph(
    [helper.make_node("Gather", ["table", "t"], ["g"]),
     helper.make_node("Unsqueeze", ["g", "axes"], ["g3"]),
     helper.make_node("Add", ["x_t", "g3"], ["pred"])],
    "broken",
    [io("x_t", T.FLOAT, ["B", 150, 72]), io("t", T.INT64, ["B"]),
     io("music", T.FLOAT, ["B", 157, 80]), io("cond", T.FLOAT, ["B"])],
    [io("pred", T.FLOAT, ["B", 150, 72])],
    [numpy_helper.from_array(np.zeros(10, np.float32), "table"),
     numpy_helper.from_array(np.array([1, 2], np.int64), "axes")])
m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 18)])
m.ir_version = 10
onnx.save(m, sys.argv[1])
manifest = sys.argv[1].replace("denoiser.onnx", "choreod-model.toml")
text = open(manifest).read()
old = text.split('sha256 = "')[1].split('"')[0]
open(manifest, "w").write(text.replace(old, hashlib.sha256(open(sys.argv[1], "rb").read()).hexdigest()))
print("ok")
"#,
        &[&s(&onnx)],
    );
    let out = run(&["models", "check", &pkg]);
    fails_with(
        &out,
        4,
        &[
            "component denoiser: run failed",
            "indices element out of data bounds",
        ],
    );
    assert!(!stderr(&out).contains('\u{1b}'), "{}", stderr(&out));
}

#[test]
fn prep_with_no_surviving_sequence_says_what_was_skipped() {
    let d = tempfile::tempdir().unwrap();
    let root = d.path().join("hml");
    py(
        "import sys, os, numpy as np\nr = sys.argv[1]\nos.makedirs(r + '/new_joints')\nfor i in ('000001', '000002'):\n    np.save(f'{r}/new_joints/{i}.npy', np.zeros((20, 22, 3), np.float32))\nopen(r + '/train.txt', 'w').write('000001\\n000002\\n')\nopen(r + '/val.txt', 'w').close()\nopen(r + '/test.txt', 'w').close()\nprint('ok')",
        &[&s(&root)],
    );
    let out_dir = d.path().join("out");
    let out = run(&["prep", "humanml3d", &s(&root), "-o", &s(&out_dir)]);
    let line = fails_with(
        &out,
        1,
        &[
            "no sequence survived: 2 skipped (2 too short)",
            "manifest.json",
        ],
    );
    assert!(!line.contains("mean/std"), "{line}");
    // The manifest it points to lists them.
    let manifest = std::fs::read_to_string(out_dir.join("manifest.json")).unwrap();
    assert!(
        manifest.contains("000001") && manifest.contains("too_short"),
        "{manifest}"
    );
    assert!(stdout(&out).is_empty() || !stdout(&out).contains("Mean.npy"));
}

/// `models/packages/exemplar` copied to `dir/endless` with a denoiser whose ONNX `Loop` runs
/// 2^62 times (`tests/tools/hostile_onnx.py`): a valid model that never finishes.
fn endless_package(dir: &Path) -> String {
    let pkg = edited_package(dir, "endless", |t| t);
    let out = python_cmd()
        .arg(workspace_root().join("tests/tools/hostile_onnx.py"))
        .args(["endless-loop", &pkg])
        .output()
        .expect("run hostile_onnx.py");
    assert!(out.status.success(), "{}", stderr(&out));
    pkg
}

/// Run choreod with `args`; a run still going after `bound` is killed and fails the test
/// (choreod before the time limits hung here for ever).
fn run_within(bound: Duration, args: &[&str]) -> Output {
    let mut child = choreod()
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn choreod");
    let started = Instant::now();
    while child.try_wait().expect("wait for choreod").is_none() {
        if started.elapsed() > bound {
            child.kill().expect("kill choreod");
            let out = child.wait_with_output().expect("reap choreod");
            panic!(
                "choreod {args:?} still running after {bound:?}: {}{}",
                stdout(&out),
                stderr(&out)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().expect("choreod output")
}

#[test]
fn a_model_that_loops_for_ever_is_stopped_at_the_time_limit() {
    let d = tempfile::tempdir().unwrap();
    let pkg = endless_package(d.path());
    // The limit plus start-up; without a limit these runs never end.
    let bound = Duration::from_secs(20);
    let started = Instant::now();
    let out = run_within(bound, &["models", "check", &pkg, "--time-limit", "2"]);
    fails_with(
        &out,
        4,
        &[&format!(
            "model package {pkg}: component denoiser: stopped at the time limit of 2 s (--time-limit)"
        )],
    );
    assert!(started.elapsed() >= Duration::from_secs(2), "stopped early");
    let song = s(&fixtures().join("audio/vibe_ace_22k_mono.ogg"));
    let output = d.path().join("dance.h5");
    let out = run_within(
        bound,
        &[
            "dance",
            &song,
            "-o",
            &s(&output),
            "--model",
            &pkg,
            "--time-limit",
            "3",
        ],
    );
    fails_with(
        &out,
        1,
        &[
            &format!("generating a dance for {song}"),
            "component denoiser: stopped at the time limit of 3 s (--time-limit)",
        ],
    );
    assert!(!output.exists());
}

#[test]
fn serve_fails_every_song_of_a_model_that_loops_for_ever_and_keeps_serving() {
    let d = tempfile::tempdir().unwrap();
    let pkg = endless_package(d.path());
    let mut home = Home::new(&format!(
        "[runtime]\ndefault_model = \"{pkg}\"\n\n[job]\nsteps = 2\ntime_limit_s = 2\n"
    ));
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    for k in 0..3 {
        drop_file(&home.inbox(), &format!("song-{k}.wav"), &wav_bytes(2.0, k));
    }
    // Two workers, three jobs of 2 s each: under 10 s; a hang would never end.
    home.wait_for_outcomes(3, &[], Duration::from_secs(60), &mut daemon);
    let reports = home.reports();
    assert_eq!(reports.len(), 3, "one outcome per song: {reports:?}");
    for r in &reports {
        let reason = r["reason"].as_str().unwrap_or_default();
        assert!(
            reason.contains(
                "component denoiser: stopped at the time limit of 2 s (job.time_limit_s)"
            ),
            "{r}"
        );
        assert_eq!(r["stage"].as_str(), Some("generate"), "{r}");
    }
    assert!(home.names("out").iter().all(|n| !n.ends_with(".h5")));
    let (status, _) = home.http_get("/healthz").expect("healthz");
    assert!(status.contains(" 200 "), "{status}");
    daemon.term();
    let exit = daemon.wait_exit(Duration::from_secs(20));
    assert!(exit.is_some_and(|e| e.success()), "{exit:?}");
}
