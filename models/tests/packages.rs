//! Model packages through ONNX Runtime: broken packages give one clear error naming package and
//! component; the `exemplar` package (K = 1, built by models/packages/build.py) is an oracle for
//! every sampler; generation is deterministic.
//!
//! Needs the project venv (`scripts/setup`): ONNX Runtime from `.venv` (or ORT_DYLIB_PATH) and
//! python with `onnx` ($CHOREOD_PYTHON or `.venv/bin/python`) to build test graphs.

// Helpers outside #[test] fns are test code too: a panic there is a failed test.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use choreo_datasets::skeleton::SMPL24_PARENTS;
use choreo_models::{
    DanceDenoiser, DanceOptions, Denoiser, Error, Guidance, Known, Manifest, ModelPackage,
    NoiseSource, OrtRuntime, Role, RuntimeOptions, SampleRequest, Sampler, SamplerKind,
    generate_dance, locate_library,
};
use ndarray::{Array2, Array3, s};

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn python() -> PathBuf {
    std::env::var_os("CHOREOD_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join(".venv/bin/python"))
}

fn ort() -> &'static OrtRuntime {
    static ORT: OnceLock<OrtRuntime> = OnceLock::new();
    ORT.get_or_init(|| {
        OrtRuntime::load(&locate_library(None)).expect("ONNX Runtime (run scripts/setup)")
    })
}

fn run_python(args: &[&std::ffi::OsStr]) {
    let out = Command::new(python())
        .args(args)
        .output()
        .expect("python (run scripts/setup)");
    assert!(
        out.status.success(),
        "python {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The graphs of make_graphs.py, built once per test run.
fn graphs() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/make_graphs.py");
        run_python(&[script.as_os_str(), dir.path().as_os_str()]);
        dir
    })
    .path()
}

/// The contract's manifest with T = 8, stride 4, 6 mel frames, for the make_graphs.py graphs
/// (shared with the unit tests).
fn manifest_text(sha256: &str) -> String {
    include_str!("data/tiny-manifest.toml").replace("@SHA256@", sha256)
}

/// A package directory with `graph` as its denoiser; `sha` overrides the true checksum.
fn package(graph: &str, sha: Option<&str>) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let src = graphs().join(graph);
    let dst = dir.path().join("denoiser.onnx");
    std::fs::copy(&src, &dst).unwrap();
    let real = choreo_datasets::sha256_file(&dst).unwrap();
    std::fs::write(
        dir.path().join("choreod-model.toml"),
        manifest_text(sha.unwrap_or(&real)),
    )
    .unwrap();
    dir
}

fn load(dir: &Path) -> choreo_models::Result<ModelPackage> {
    ModelPackage::load(dir, &RuntimeOptions::default(), ort())
}

/// The error's one line names the package directory and the component.
fn assert_names_package(e: &Error, dir: &Path, words: &[&str]) {
    let msg = e.to_string();
    assert!(e.is_environment(), "{msg}");
    assert!(
        msg.contains(&dir.display().to_string()),
        "no package in: {msg}"
    );
    assert!(msg.contains("component denoiser"), "no component in: {msg}");
    for w in words {
        assert!(msg.contains(w), "no {w:?} in: {msg}");
    }
    assert!(!msg.contains('\n'), "not one line: {msg}");
}

#[test]
fn a_good_package_loads_runs_and_summarises() {
    let dir = package("good.onnx", None);
    let mut p = load(dir.path()).unwrap();
    p.smoke_test().unwrap();
    let summary = p.to_string();
    assert!(
        summary.contains("tiny") && summary.contains("x_t") && summary.contains("[N, 6, 80]"),
        "{summary}"
    );
    let mel = Array2::<f32>::from_elem((80, 40), -50.0);
    let mut calls = 0;
    let dance = generate_dance(&mut p, mel.view(), &DanceOptions::default(), &mut |_, _| {
        calls += 1
    })
    .unwrap();
    // 39 hops of 512 at 16 kHz = 1.248 s → round(37.44) = 37 frames.
    assert_eq!(dance.joints.dim(), (37, 24, 3));
    // One progress call and one batched evaluation per step of the manifest's sampler.
    let steps = p.manifest().sampler_options().steps;
    assert_eq!(steps, 10);
    assert_eq!(calls, steps);
    assert_eq!(dance.stats.evaluations, steps);
    assert!(dance.stats.ort_seconds > 0.0 && dance.stats.ort_seconds <= dance.stats.total_seconds);
}

#[test]
fn a_missing_file_names_package_and_component() {
    let dir = package("good.onnx", None);
    std::fs::remove_file(dir.path().join("denoiser.onnx")).unwrap();
    let e = load(dir.path()).unwrap_err();
    assert_names_package(&e, dir.path(), &["denoiser.onnx"]);
}

#[test]
fn wrong_tensor_names_name_the_tensor() {
    let dir = package("renamed.onnx", None);
    let e = load(dir.path()).unwrap_err();
    assert_names_package(&e, dir.path(), &["x_t", "xt"]);
}

#[test]
fn a_fixed_batch_axis_is_refused() {
    let dir = package("fixed_batch.onnx", None);
    let e = load(dir.path()).unwrap_err();
    assert_names_package(&e, dir.path(), &["dynamic"]);
}

#[test]
fn corrupt_onnx_bytes_are_a_load_error() {
    let dir = package("corrupt.onnx", None);
    let e = load(dir.path()).unwrap_err();
    assert_names_package(&e, dir.path(), &["cannot load"]);
}

#[test]
fn an_unsupported_opset_is_a_load_error() {
    let dir = package("future_opset.onnx", None);
    let e = load(dir.path()).unwrap_err();
    assert_names_package(&e, dir.path(), &["cannot load", "opset"]);
}

#[test]
fn a_changed_file_fails_the_checksum() {
    let dir = package("good.onnx", Some(&"ab".repeat(32)));
    let e = load(dir.path()).unwrap_err();
    assert_names_package(&e, dir.path(), &["sha256", &"ab".repeat(32)]);
}

#[test]
fn a_graph_that_outputs_nan_is_caught() {
    let dir = package("nan.onnx", None);
    let mut p = load(dir.path()).unwrap();
    let e = p.smoke_test().unwrap_err();
    assert_names_package(&e, dir.path(), &["NaN", "pred"]);
}

// ---------------------------------------------------------------------------------------------
// The exemplar package.

fn build_script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("packages/build.py")
}

/// `exemplar` with one window, built into a temp dir by the package script.
fn exemplar_k1() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("exemplar-k1");
        run_python(&[
            build_script().as_os_str(),
            "exemplar".as_ref(),
            "--exemplars".as_ref(),
            "1".as_ref(),
            "--out".as_ref(),
            out.as_os_str(),
        ]);
        dir
    })
    .path()
    .join("exemplar-k1")
    .leak()
}

/// The package's one exemplar, read off the network: with K = 1 the x0 estimate is the
/// exemplar at any x_t, so x0 = (x_t - sqrt(1 - ab) eps) / sqrt(ab) at t = 0 and x_t = 0.
fn exemplar_of(p: &mut ModelPackage) -> Array2<f32> {
    let m = p.manifest().clone();
    let ab0 = m.schedule().unwrap().alphas_cumprod()[0];
    let (w, d) = (m.dance_spec().unwrap().window_frames, m.motion.dim);
    let x = Array3::<f32>::zeros((1, w, d));
    let music = Array3::<f32>::from_elem(
        (
            1,
            m.dance_spec().unwrap().audio.music_frames,
            m.dance_spec().unwrap().audio.n_mels,
        ),
        -40.0,
    );
    let eps = DanceDenoiser::new(p.component(Role::Denoiser).unwrap())
        .predict(x.view(), &[0], music.view(), &[1.0])
        .unwrap();
    eps.slice(s![0, .., ..])
        .mapv(|e| (-(1.0 - ab0).sqrt() * f64::from(e) / ab0.sqrt()) as f32)
}

fn music_batch(m: &Manifest, n: usize) -> Array3<f32> {
    Array3::from_shape_fn(
        (
            n,
            m.dance_spec().unwrap().audio.music_frames,
            m.dance_spec().unwrap().audio.n_mels,
        ),
        |(i, f, b)| -80.0 + ((i * 13 + f * 7 + b * 3) % 70) as f32,
    )
}

#[test]
fn exemplar_k1_is_an_oracle_for_every_sampler() {
    let mut p = load(exemplar_k1()).unwrap();
    let e = exemplar_of(&mut p);
    let m = p.manifest().clone();
    let (w, d) = (m.dance_spec().unwrap().window_frames, m.motion.dim);
    let n = 2;
    let music = music_batch(&m, n);
    // In-painting: 20 known frames off the exemplar by +0.3, so they are visibly forced.
    let mut values = Array3::<f32>::zeros((n, w, d));
    let mut mask = Array3::from_elem((n, w, d), false);
    for i in 0..n {
        values
            .slice_mut(s![i, ..20, ..])
            .assign(&e.slice(s![..20, ..]).mapv(|v| v + 0.3));
        mask.slice_mut(s![i, ..20, ..]).fill(true);
    }
    let emax = e.iter().fold(0f32, |a, b| a.max(b.abs()));
    for (kind, steps, offset, eta) in [
        (SamplerKind::Ddpm, 100, 0, 0.0),
        (SamplerKind::Ddim, 50, 1, 0.0),
        (SamplerKind::Ddim, 50, 1, 1.0),
    ] {
        for guidance in [Guidance::Off, Guidance::Single(2.5)] {
            for inpaint in [false, true] {
                let mut o = m.sampler_options();
                (o.kind, o.steps, o.steps_offset, o.eta, o.guidance) =
                    (kind, steps, offset, eta, guidance);
                o.set_alpha_to_one = true;
                let sampler = Sampler::new(m.schedule().unwrap(), o).unwrap();
                let known = inpaint.then(|| Known {
                    values: values.view(),
                    mask: mask.view(),
                    exact: true,
                });
                let req = SampleRequest {
                    music: music.view(),
                    window: (w, d),
                    known,
                    chain_overlap: 0,
                    init: None,
                };
                let (x, stats) = sampler
                    .sample(
                        &mut DanceDenoiser::new(p.component(Role::Denoiser).unwrap()),
                        &req,
                        &mut NoiseSource::new(7, 0),
                        &mut |_, _| {},
                    )
                    .unwrap();
                let label = format!("{kind:?} eta {eta} {guidance:?} inpaint {inpaint}");
                assert_eq!(stats.calls, steps, "{label}");
                let from = if inpaint { 20 } else { 0 };
                let mut err = 0f32;
                for i in 0..n {
                    for (a, b) in x
                        .slice(s![i, from.., ..])
                        .iter()
                        .zip(e.slice(s![from.., ..]).iter())
                    {
                        err = err.max((a - b).abs());
                    }
                }
                // f32 network: eps carries ~1e-7 relative rounding; x0 is re-estimated at every
                // step and the last step (t = 0 or 1, sqrt(1 - ab) <= 0.015) scales eps errors
                // down, so 1e-3 of the exemplar's range is generous and still catches any wrong
                // coefficient (those err by >= 1e-2 at the last step).
                assert!(err < 1e-3 * emax.max(1.0), "{label}: max error {err}");
                if inpaint {
                    assert_eq!(
                        x.slice(s![.., ..20, ..]),
                        values.slice(s![.., ..20, ..]),
                        "{label}"
                    );
                }
            }
        }
    }
}

#[test]
fn the_shipped_exemplar_is_deterministic_and_finite() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("packages/exemplar");
    let mut p = load(&dir).unwrap();
    p.smoke_test().unwrap();
    // 12 s of a synthetic mel: a beat-like energy pulse every 16 frames (~2 Hz).
    let frames = (12.0 * 31.25) as usize + 1;
    let mel = Array2::from_shape_fn((80, frames), |(b, f)| {
        if f % 16 < 3 {
            -20.0 - b as f32 * 0.2
        } else {
            -60.0 - b as f32 * 0.2
        }
    });
    let mut opts = DanceOptions::default();
    (opts.seed, opts.steps, opts.chunk_windows) = (3, Some(10), 2);
    let a = generate_dance(&mut p, mel.view(), &opts, &mut |_, _| {}).unwrap();
    let b = generate_dance(&mut p, mel.view(), &opts, &mut |_, _| {}).unwrap();
    assert_eq!(a.joints.dim(), (360, 24, 3));
    assert_eq!(a.joints, b.joints, "same seed, same dance");
    assert!(a.joints.iter().all(|v| v.is_finite()));
    let mut other = opts.clone();
    other.seed = 4;
    let c = generate_dance(&mut p, mel.view(), &other, &mut |_, _| {}).unwrap();
    assert_ne!(a.joints, c.joints, "another seed, another dance");
}

/// Per frame f >= 1: the largest joint displacement from frame f - 1 (metres per frame).
fn frame_jumps(joints: &Array3<f32>) -> Vec<f32> {
    (1..joints.dim().0)
        .map(|f| {
            (0..24)
                .map(|j| {
                    (0..3)
                        .map(|c| (joints[[f, j, c]] - joints[[f - 1, j, c]]).powi(2))
                        .sum::<f32>()
                        .sqrt()
                })
                .fold(0f32, f32::max)
        })
        .collect()
}

#[test]
fn window_and_chunk_seams_do_not_jump() {
    // 30 s: 11 windows, chunks of 3, so the seams include chunk borders (in-painted seeds).
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("packages/exemplar");
    let mut p = load(&dir).unwrap();
    let m = p.manifest().clone();
    let frames = (30.0 * m.dance_spec().unwrap().audio.frame_rate()) as usize + 1;
    let mel = Array2::from_shape_fn((80, frames), |(b, f)| {
        if f % 15 < 3 {
            -15.0 - b as f32 * 0.25
        } else {
            -55.0 - b as f32 * 0.25
        }
    });
    let mut opts = DanceOptions::default();
    (opts.seed, opts.chunk_windows) = (11, 3);
    let dance = generate_dance(&mut p, mel.view(), &opts, &mut |_, _| {}).unwrap();
    assert_eq!(dance.joints.dim().0, 900);
    let jumps = frame_jumps(&dance.joints);
    let mut sorted = jumps.clone();
    sorted.sort_by(f32::total_cmp);
    let p99 = sorted[(0.99 * (sorted.len() - 1) as f64).round() as usize];
    let (stride, overlap) = (
        m.dance_spec().unwrap().stride_frames,
        m.dance_spec().unwrap().overlap_frames(),
    );
    // Either the per-step overlap copy or the cross-fade alone keeps this (checked by removing
    // each); removing both fails it.
    // Seams: where a window's fade-in starts and ends (window i starts at i·stride). A jump is
    // a step above the dance's 99th percentile that also stands out from the steps two frames
    // before and after it by 1.5x: at 30 fps a fast movement is fast over several frames (the
    // exemplar's arm swing peaking at 0.136 m on a seam between steps of 0.127 and 0.135 m), a
    // discontinuity is one frame.
    for i in 1..dance.stats.windows {
        for seam in [i * stride, i * stride + overlap] {
            if seam >= 3 && seam + 2 < jumps.len() {
                let jump = jumps[seam - 1];
                let around = jumps[seam - 3].max(jumps[seam + 1]);
                assert!(
                    jump <= p99 || jump <= 1.5 * around,
                    "window {i}: jump {jump} m at frame {seam} > p99 {p99} m and > 1.5 x {around} m"
                );
            }
        }
    }
}

/// A little-endian float32 C-order `.npy` (the shared reference fixtures): shape and values.
fn read_npy_f32(path: &Path) -> (Vec<usize>, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..6], b"\x93NUMPY", "{}", path.display());
    let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = std::str::from_utf8(&bytes[10..10 + header_len]).unwrap();
    assert!(
        header.contains("'<f4'") && header.contains("'fortran_order': False"),
        "{header}"
    );
    let inside = &header[header.find("'shape': (").unwrap() + 10..];
    let shape: Vec<usize> = inside[..inside.find(')').unwrap()]
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse().unwrap())
        .collect();
    let data = bytes[10 + header_len..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    (shape, data)
}

#[test]
fn a_real_sixty_second_song_dances_with_a_rigid_skeleton() {
    let reference = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/fixtures/reference");
    let (shape, values) = read_npy_f32(&reference.join("vibe_ace_44k_stereo.logmel.npy"));
    let mel = Array2::from_shape_vec((shape[0], shape[1]), values).unwrap();
    let (samples, _) = read_npy_f32(&reference.join("vibe_ace_44k_stereo.wav16k.npy"));
    let duration_s = samples[0] as f64 / 16000.0;
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("packages/exemplar");
    let mut p = load(&dir).unwrap();
    let mut opts = DanceOptions::default();
    opts.duration_s = Some(duration_s);
    let dance = generate_dance(&mut p, mel.view(), &opts, &mut |_, _| {}).unwrap();
    let frames = dance.joints.dim().0;
    assert_eq!(frames, (duration_s * 30.0).round() as usize);
    assert!(dance.joints.iter().all(|v| v.is_finite()));
    // Bones: each window is real SMPL forward kinematics (constant lengths) and the stitch
    // turns bone directions, so lengths may only move by f32 rounding; 1 mm is generous.
    for (j, &parent) in SMPL24_PARENTS.iter().enumerate().skip(1) {
        let parent = parent as usize;
        let lengths: Vec<f32> = (0..frames)
            .map(|f| {
                (0..3)
                    .map(|c| (dance.joints[[f, j, c]] - dance.joints[[f, parent, c]]).powi(2))
                    .sum::<f32>()
                    .sqrt()
            })
            .collect();
        let (lo, hi) = lengths
            .iter()
            .fold((f32::INFINITY, 0f32), |(a, b), &l| (a.min(l), b.max(l)));
        assert!(
            hi - lo < 1e-3,
            "bone {parent}->{j} length varies by {} m",
            hi - lo
        );
    }
    // Sibling spans (issue 12 item 15): stitching turns each bone on its own, which bent the
    // collar (13-14) and hip (1-2) spans by up to 13 mm; after the rigid fit every frame is a
    // pose of one skeleton, so they stay within f32 rounding of FK (1e-4 m).
    for (a, b) in [(13, 14), (12, 13), (1, 2), (1, 3)] {
        let spans: Vec<f32> = (0..frames)
            .map(|f| {
                (0..3)
                    .map(|c| (dance.joints[[f, a, c]] - dance.joints[[f, b, c]]).powi(2))
                    .sum::<f32>()
                    .sqrt()
            })
            .collect();
        let (lo, hi) = spans
            .iter()
            .fold((f32::INFINITY, 0f32), |(x, y), &l| (x.min(l), y.max(l)));
        assert!(hi - lo < 1e-4, "span {a}-{b} varies by {} m", hi - lo);
    }
    // Feet: the lowest of ankles and toes (joints 7, 8, 10, 11) is on the floor (y = 0, where
    // the package puts the source's lowest foot) in most frames; a dance has hops, so 99 % of
    // frames within 15 cm and none below -2 cm.
    let mut feet: Vec<f32> = (0..frames)
        .map(|f| {
            [7, 8, 10, 11]
                .iter()
                .map(|&j| dance.joints[[f, j, 1]])
                .fold(f32::INFINITY, f32::min)
        })
        .collect();
    feet.sort_by(f32::total_cmp);
    assert!(feet[0] > -0.02, "a foot {} m below the floor", feet[0]);
    let p99 = feet[frames * 99 / 100];
    assert!(
        p99 < 0.15,
        "99th percentile of the lowest foot: {p99} m above the floor"
    );
    // Seams: no frame-to-frame jump at a window seam that stands out from the motion around it:
    // at most the largest other step within 1 s plus the motion's own 99th percentile of the
    // change between consecutive steps (a discontinuity of a few cm fails it). Local, not the
    // whole dance's 99th percentile step: the default package plays its dance at the song's
    // tempo, window by window (0.6x-1.25x), so a fast stretch's natural steps exceed a slow
    // stretch's (vibe_ace: a hand swing peaking at the frame-1650 seam, 0.20 m against the
    // dance's p99 of 0.19 m and 0.19-0.20 m in the frames beside it).
    let jumps = frame_jumps(&dance.joints);
    let mut changes: Vec<f32> = jumps.windows(2).map(|w| (w[1] - w[0]).abs()).collect();
    changes.sort_by(f32::total_cmp);
    let change_p99 = changes[(0.99 * (changes.len() - 1) as f64).round() as usize];
    let m = p.manifest();
    for i in 1..dance.stats.windows {
        for seam in [
            i * m.dance_spec().unwrap().stride_frames,
            i * m.dance_spec().unwrap().stride_frames + m.dance_spec().unwrap().overlap_frames(),
        ] {
            if seam >= 1 && seam < jumps.len() {
                let around = (seam.saturating_sub(31)..(seam + 30).min(jumps.len()))
                    .filter(|&f| f != seam - 1)
                    .map(|f| jumps[f])
                    .fold(0f32, f32::max);
                assert!(
                    jumps[seam - 1] <= around + change_p99,
                    "seam at frame {seam}: {} m > {around} m (largest step within 1 s) + {change_p99} m",
                    jumps[seam - 1]
                );
            }
        }
    }
}

#[test]
fn stored_weight_counts_match_the_onnx_python_package() {
    let script = "import sys, onnx, numpy as np\n\
        m = onnx.load(sys.argv[1])\n\
        n = sum(int(np.prod(t.dims)) for t in m.graph.initializer)\n\
        n += sum(int(np.prod(a.t.dims)) for nd in m.graph.node for a in nd.attribute if a.type == onnx.AttributeProto.TENSOR)\n\
        print(n, m.ir_version, m.opset_import[0].version)";
    for name in ["exemplar", "mofusion-ref"] {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("packages")
            .join(name);
        let p = load(&dir).unwrap();
        let info = p.components().next().unwrap().onnx_info().unwrap().clone();
        let out = Command::new(python())
            .args(["-c", script])
            .arg(dir.join("denoiser.onnx"))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let want = String::from_utf8(out.stdout).unwrap();
        let got = format!(
            "{} {} {}\n",
            info.stored_values, info.ir_version, info.opsets[0].1
        );
        assert_eq!(got, want, "{name}");
        assert!(p.to_string().contains("stored weight values"));
    }
}

fn load_hoisted(dir: &Path, hoist: bool) -> ModelPackage {
    let mut options = RuntimeOptions::default();
    options.hoist_invariants = hoist;
    ModelPackage::load(dir, &options, ort()).unwrap()
}

/// Largest |a - b| relative to the largest |b| (at least 1).
fn relative_gap(a: &Array3<f32>, b: &Array3<f32>) -> f32 {
    assert_eq!(a.dim(), b.dim());
    let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
    a.iter()
        .zip(b)
        .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()))
        / scale
}

/// Hoisting splits the denoiser graph into a prologue (run once per batch of music) and a step
/// graph holding the same nodes, so each call must give what the whole graph gives. Tolerance
/// 1e-5 of the output scale: ONNX Runtime may fuse operators differently on either side of the
/// split (summation order), which moves float32 results by a few ulps; a wrong split (a tensor
/// from another batch, a missing node) moves them by O(1).
#[test]
fn hoisted_denoisers_compute_what_the_whole_graph_computes() {
    // Frontier sizes: the exemplar hands over its beat-retimed candidates (whole, and the first
    // half its data term reads) and their music logits; mofusion-ref the keys and the values of
    // each of its 7 cross-attention blocks.
    for (name, frontier) in [("exemplar", 3), ("mofusion-ref", 14)] {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("packages")
            .join(name);
        let mut split = load_hoisted(&dir, true);
        let mut whole = load_hoisted(&dir, false);
        assert!(
            whole
                .component(Role::Denoiser)
                .unwrap()
                .hoisting()
                .is_none()
        );
        let h = split
            .component(Role::Denoiser)
            .unwrap()
            .hoisting()
            .expect("hoisted");
        assert_eq!(h.frontier_tensors, frontier, "{name}");
        assert!(
            h.hoisted_nodes > 0 && h.hoisted_nodes < h.total_nodes,
            "{h:?}"
        );
        let m = split.manifest().clone();
        let (w, d) = (m.dance_spec().unwrap().window_frames, m.motion.dim);
        let music_a = music_batch(&m, 3);
        let music_b = music_a.mapv(|v| -80.0 - v);
        let cond = [1.0, 0.0, 1.0];
        // A, B, A again (a cache hit after a miss), with new x_t and t every call.
        for (k, music) in [&music_a, &music_b, &music_a, &music_a]
            .into_iter()
            .enumerate()
        {
            let x = Array3::from_shape_fn((3, w, d), |(i, f, c)| {
                ((i * 31 + f * 7 + c * 3 + k * 11) % 17) as f32 / 8.0 - 1.0
            });
            let t = [999 - 300 * k as i64; 3];
            let a = DanceDenoiser::new(split.component(Role::Denoiser).unwrap())
                .predict(x.view(), &t, music.view(), &cond)
                .unwrap();
            let b = DanceDenoiser::new(whole.component(Role::Denoiser).unwrap())
                .predict(x.view(), &t, music.view(), &cond)
                .unwrap();
            let gap = relative_gap(&a, &b);
            assert!(gap <= 1e-5, "{name} call {k}: relative gap {gap}");
        }
        let h = split.component(Role::Denoiser).unwrap().hoisting().unwrap();
        assert_eq!(h.prologue_runs, 2, "{name}: music A and B once each");
    }
}

/// A whole generation with guidance, batched and in two calls, gives the same joints with and
/// without hoisting, running the prologue once per chunk and row group. Tolerance 1e-4 m: the
/// per-call gaps above (≤ 1e-5 relative) pass through 10 sampler steps.
#[test]
fn hoisting_leaves_the_dance_unchanged() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("packages/mofusion-ref");
    let frames = (12.0 * 31.25) as usize + 1;
    let mel = Array2::from_shape_fn((80, frames), |(b, f)| -80.0 + ((b * 5 + f * 3) % 60) as f32);
    for batched in [true, false] {
        let mut opts = DanceOptions::default();
        (opts.steps, opts.chunk_windows, opts.guidance) = (Some(10), 2, Some(2.0));
        opts.batch_guidance = batched;
        let mut split = load_hoisted(&dir, true);
        let mut whole = load_hoisted(&dir, false);
        let a = generate_dance(&mut split, mel.view(), &opts, &mut |_, _| {}).unwrap();
        let b = generate_dance(&mut whole, mel.view(), &opts, &mut |_, _| {}).unwrap();
        let gap = a
            .joints
            .iter()
            .zip(&b.joints)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(gap <= 1e-4, "batched {batched}: joints differ by {gap} m");
        let runs = split
            .component(Role::Denoiser)
            .unwrap()
            .hoisting()
            .unwrap()
            .prologue_runs;
        let groups = if batched { 1 } else { 2 };
        assert_eq!(runs, a.stats.chunks * groups, "batched {batched}");
        assert!(a.stats.chunks > 1);
    }
}
