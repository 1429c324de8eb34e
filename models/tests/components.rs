//! The runtime layer's generic [`Component::run`] on real style-transfer packages: named inputs
//! checked by name, dtype and shape (symbolic axes bound once per call) before ONNX Runtime
//! sees them, outputs checked finite, and step-invariant work hoisted for any looped
//! component, keyed by all its constant inputs.
//!
//! Needs ONNX Runtime from `.venv` (or ORT_DYLIB_PATH), as `scripts/setup` installs it.

// Helpers outside #[test] fns are test code too: a panic there is a failed test.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use std::time::Duration;

use choreo_models::{
    Deadline, Error, ModelPackage, NamedTensors, OrtRuntime, Role, RuntimeOptions, TensorView,
    locate_library,
};
use ndarray::{Array2, Array3, ArrayD, aview1};

fn ort() -> &'static OrtRuntime {
    static ORT: OnceLock<OrtRuntime> = OnceLock::new();
    ORT.get_or_init(|| {
        OrtRuntime::load(&locate_library(None)).expect("ONNX Runtime (run scripts/setup)")
    })
}

fn package_dir(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("packages")
        .join(name)
}

fn load(name: &str, hoist: bool) -> ModelPackage {
    let mut options = RuntimeOptions::default();
    options.hoist_invariants = hoist;
    ModelPackage::load(&package_dir(name), &options, ort()).unwrap()
}

/// HumanML3D-shaped features (N, T, 263) that differ per row, frame and channel.
fn features(n: usize, frames: usize, phase: usize) -> Array3<f32> {
    Array3::from_shape_fn((n, frames, 263), |(i, f, c)| {
        if c < 4 {
            0.0
        } else {
            0.01 * ((i * 11 + f * 7 + c * 3 + phase) % 61) as f32 - 0.3
        }
    })
}

/// The typed error of a refused call: which tensor, and the message.
fn refused(result: choreo_models::Result<NamedTensors>) -> (String, String) {
    match result {
        Err(e @ Error::Tensor { .. }) => {
            let msg = e.to_string();
            let Error::Tensor { tensor, .. } = e else {
                unreachable!()
            };
            (tensor, msg)
        }
        other => panic!("expected a tensor error, got {other:?}"),
    }
}

#[test]
fn run_checks_names_dtypes_and_shapes_against_the_manifest() {
    let mut p = load("style-gaussian", false);
    let encoder = p.component(Role::VaeEncoder).unwrap();
    let x = features(2, 12, 0);
    let mask = Array2::<f32>::ones((2, 12));
    let mut out = encoder
        .run(&[("features", x.view().into()), ("mask", mask.view().into())])
        .unwrap();
    // style-gaussian's latent is [N, T, 284]: N and T bound by the inputs.
    assert_eq!(out.get("latent").unwrap().shape(), &[2, 12, 284]);
    assert_eq!(out.take("latent").unwrap().shape(), &[2, 12, 284]);
    assert!(out.take("latent").is_err(), "taken twice");

    let mask_i64 = Array2::<i64>::ones((2, 12));
    let short_mask = Array2::<f32>::ones((2, 10));
    let narrow = Array3::<f32>::zeros((2, 12, 262));
    let flat = Array2::<f32>::zeros((2, 12));
    // (inputs, the tensor the error names, why)
    type Case<'a> = (Vec<(&'a str, TensorView<'a>)>, &'a str, &'a str);
    let cases: Vec<Case<'_>> = vec![
        (
            vec![("feature", x.view().into()), ("mask", mask.view().into())],
            "feature",
            "not an input",
        ),
        (vec![("features", x.view().into())], "mask", "missing"),
        (
            vec![
                ("features", x.view().into()),
                ("mask", mask.view().into()),
                ("style", mask.view().into()),
            ],
            "style",
            "not an input",
        ),
        (
            vec![
                ("features", x.view().into()),
                ("mask", mask.view().into()),
                ("mask", mask.view().into()),
            ],
            "mask",
            "twice",
        ),
        (
            vec![
                ("features", x.view().into()),
                ("mask", mask_i64.view().into()),
            ],
            "mask",
            "is int64, the manifest says float32",
        ),
        (
            vec![
                ("features", narrow.view().into()),
                ("mask", mask.view().into()),
            ],
            "features",
            "axis 2 is 262, expected 263",
        ),
        (
            vec![
                ("features", flat.view().into()),
                ("mask", mask.view().into()),
            ],
            "features",
            "rank 2, expected 3",
        ),
        // T is 12 in `features`, so a 10-frame mask contradicts it.
        (
            vec![
                ("features", x.view().into()),
                ("mask", short_mask.view().into()),
            ],
            "mask",
            "(T) is 10, but T is 12",
        ),
    ];
    for (inputs, tensor, why) in cases {
        let (got, msg) = refused(encoder.run(&inputs));
        assert_eq!(got, tensor, "{msg}");
        assert!(
            msg.contains(&format!("tensor {tensor}")) && msg.contains(why),
            "expected {why:?} about {tensor}: {msg}"
        );
        assert!(msg.contains("component vae_encoder"), "{msg}");
    }
    // The batch axis binds across inputs too.
    let one_row_mask = Array2::<f32>::ones((1, 12));
    let (got, msg) = refused(encoder.run(&[
        ("features", x.view().into()),
        ("mask", one_row_mask.view().into()),
    ]));
    assert!(
        got == "mask" && msg.contains("(N) is 1, but N is 2"),
        "{msg}"
    );
    // Nothing refused reached ONNX Runtime.
    assert_eq!(encoder.runs(), 1);
}

#[test]
fn non_finite_outputs_are_a_typed_error_naming_the_output() {
    let mut p = load("style-gaussian", false);
    let mut x = features(1, 8, 0);
    x[[0, 3, 40]] = f32::NAN;
    let mask = Array2::<f32>::ones((1, 8));
    let e = p
        .component(Role::VaeEncoder)
        .unwrap()
        .run(&[("features", x.view().into()), ("mask", mask.view().into())])
        .unwrap_err();
    match &e {
        Error::NonFinite {
            tensor,
            count,
            timestep,
            ..
        } => assert!(
            tensor == "latent" && *count > 0 && timestep.is_none(),
            "{e}"
        ),
        other => panic!("expected NonFinite, got {other:?}"),
    }
    assert!(e.to_string().contains("output latent"), "{e}");
}

/// The style-transfer denoiser with `content` and `style` varied: hoisted (the prologue keyed
/// by every constant input: content, trajectory, mask, style) it agrees with the whole graph
/// and reruns the prologue only when one of them changes.
#[test]
fn a_style_denoiser_is_hoisted_and_keyed_by_all_its_constant_inputs() {
    let mut split = load("mcm-ldm-ref", true);
    let mut whole = load("mcm-ldm-ref", false);
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
        .expect("the trajectory encoder hoists");
    assert!(
        h.hoisted_nodes > 0 && h.hoisted_nodes < h.total_nodes,
        "{h:?}"
    );
    // Encoders are not run in a loop: never split.
    assert!(
        split
            .component(Role::VaeEncoder)
            .unwrap()
            .hoisting()
            .is_none()
    );
    let frames = 40;
    let mask = Array2::<f32>::ones((2, frames));
    let trajectory =
        Array3::<f32>::from_shape_fn((2, frames, 3), |(i, f, c)| 0.02 * (f + c + i) as f32);
    let content_a = ArrayD::<f32>::from_shape_fn(vec![2, 7, 16], |d| {
        ((d[0] * 5 + d[1] * 3 + d[2]) % 13) as f32 / 6.0 - 1.0
    });
    let content_b = content_a.mapv(|v| -v);
    let style_a = Array2::<f32>::from_shape_fn((2, 32), |(i, k)| ((i + k) % 7) as f32 / 7.0);
    let style_b = style_a.mapv(|v| 1.0 - v);
    // A, B (content changes), C (only the style changes), A again (a cache hit).
    let calls = [
        (&content_a, &style_a),
        (&content_b, &style_a),
        (&content_a, &style_b),
        (&content_a, &style_a),
    ];
    for (k, (content, style)) in calls.into_iter().enumerate() {
        let x_t = ArrayD::<f32>::from_shape_fn(vec![2, 7, 16], |d| {
            ((d[0] * 31 + d[1] * 7 + d[2] * 3 + k * 11) % 17) as f32 / 8.0 - 1.0
        });
        let t = [999 - 300 * k as i64; 2];
        let inputs = [
            ("x_t", x_t.view().into()),
            ("t", aview1(&t).into()),
            ("content", content.view().into()),
            ("trajectory", trajectory.view().into()),
            ("mask", mask.view().into()),
            ("style", style.view().into()),
        ];
        let a = split
            .component(Role::Denoiser)
            .unwrap()
            .run(&inputs)
            .unwrap()
            .take("pred")
            .unwrap();
        let b = whole
            .component(Role::Denoiser)
            .unwrap()
            .run(&inputs)
            .unwrap()
            .take("pred")
            .unwrap();
        // ONNX Runtime may fuse operators differently on either side of the split, which moves
        // float32 results by a few ulps; a stale prologue result moves them by O(1).
        let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
        let gap = a
            .iter()
            .zip(&b)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(gap <= 1e-5 * scale, "call {k}: gap {gap}");
    }
    let runs = split
        .component(Role::Denoiser)
        .unwrap()
        .hoisting()
        .unwrap()
        .prologue_runs;
    assert_eq!(runs, 3, "content A, content B, style B once each");
}

#[test]
fn every_style_package_loads_and_runs_each_component() {
    for name in ["style-gaussian", "style-gaussian-oracle", "mcm-ldm-ref"] {
        let mut p = load(name, true);
        let preds = p.smoke_test().unwrap();
        assert_eq!(preds.len(), 2, "{name}");
        let latent = &p.manifest().components[&Role::Denoiser].outputs[0].shape;
        assert_eq!(preds[0].ndim(), latent.len(), "{name}");
        assert_eq!(p.components().count(), 4);
        for c in p.components() {
            assert!(c.runs() >= 1, "{name}: {} never ran", c.name());
        }
        if let Some(gap) = p.verify_hoisting(ort()).unwrap() {
            assert!(gap <= 1e-5, "{name}: {gap}");
        }
    }
    let mut dance = load("exemplar", true);
    let msg = dance.component(Role::VaeEncoder).unwrap_err().to_string();
    assert!(msg.contains("components.vae_encoder"), "{msg}");
}

/// One denoiser call of `exemplar` on `n` windows (zeros, a mel ramp, conditioned).
fn exemplar_call(package: &mut ModelPackage, n: usize) -> choreo_models::Result<ArrayD<f32>> {
    let x = Array3::<f32>::zeros((n, 150, 72));
    let music = Array3::<f32>::from_shape_fn((n, 157, 80), |(i, f, b)| {
        -80.0 + ((i + f * 7 + b * 3) % 61) as f32
    });
    let t = ndarray::Array1::<i64>::from_elem(n, 500);
    let cond = ndarray::Array1::<f32>::ones(n);
    package
        .component(Role::Denoiser)?
        .run(&[
            ("x_t", x.view().into()),
            ("t", t.view().into()),
            ("music", music.view().into()),
            ("cond", cond.view().into()),
        ])?
        .take("pred")
}

#[test]
fn a_deadline_stops_a_run_and_the_next_run_starts_clean() {
    let mut p = load("exemplar", false);
    let started = std::time::Instant::now();
    let want = exemplar_call(&mut p, 64).unwrap();
    let took = started.elapsed();
    // A deadline that passes while ONNX Runtime works: the watchdog stops the run (ONNX
    // Runtime looks at the flag between nodes, so a run in its last node may still finish:
    // earlier deadlines then).
    let stopped = [2, 4, 8, 16].into_iter().any(|fraction| {
        p.set_deadline(Some(Deadline::after(took / fraction)));
        let started = std::time::Instant::now();
        match exemplar_call(&mut p, 64) {
            Err(e @ Error::TimeLimit { .. }) => {
                let msg = e.to_string();
                assert!(
                    msg.contains("component denoiser: stopped at the time limit"),
                    "{msg}"
                );
                started.elapsed() < took
            }
            Err(e) => panic!("{e}"),
            Ok(_) => false,
        }
    });
    assert!(stopped, "no run of {took:?} was stopped part way");
    // Runs after it (the daemon's next job) are not stopped by the flag that stopped this one.
    p.set_deadline(Some(Deadline::after(Duration::from_secs(600))));
    assert_eq!(exemplar_call(&mut p, 64).unwrap(), want);
    p.set_deadline(None);
    assert_eq!(exemplar_call(&mut p, 64).unwrap(), want);
    // A deadline already passed fails the run before it starts.
    p.set_deadline(Some(Deadline::after(Duration::ZERO)));
    let e = exemplar_call(&mut p, 1).unwrap_err();
    assert!(matches!(e, Error::TimeLimit { .. }), "{e}");
}
