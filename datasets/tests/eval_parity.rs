//! `choreod eval`'s metrics against numbers the reference code computed on the same joints
//! (`fixtures/eval/reference_numbers.json`, made by `fixtures/eval/make_reference_numbers.py`
//! from google/aistplusplus_api, lisiyao21/Bailando, google-research/mint, Stanford-TML/EDGE
//! and korrawe/guided-motion-diffusion).

use std::path::{Path, PathBuf};

use choreo_datasets::metrics::{EvalInput, EvalMotion, SetValue};
use choreo_datasets::{EvalOptions, MotionFile, SkeletonKind, evaluate, read_npy};
use ndarray::{Array3, Axis, Ix3, s};
use serde_json::Value;

const WINDOW: usize = 200;
const GEN: [&str; 8] = [
    "w0", "w20", "w40", "w60", "w80", "w100", "mirror10", "rev30",
];

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/eval")
        .join(name)
}

fn reference() -> Value {
    let text =
        std::fs::read_to_string(fixture("reference_numbers.json")).expect("reference numbers");
    serde_json::from_str(&text).expect("json")
}

fn mirrored(a: Array3<f32>) -> Array3<f32> {
    let mut m = a;
    m.slice_mut(s![.., .., 0]).mapv_inplace(|x| -x);
    m
}

/// The same motions as make_reference_numbers.py `cases()`: exact float32 operations on the
/// base joints, so both sides see identical arrays.
fn cases() -> Vec<(String, Array3<f32>, f32)> {
    let base = read_npy(&fixture("base_joints.npy"))
        .expect("base joints")
        .into_dimensionality::<Ix3>()
        .expect("(T, 24, 3)");
    let win = |s: usize| base.slice(s![s..s + WINDOW, .., ..]).to_owned();
    let mut out = Vec::new();
    for s in (0..=100).step_by(20) {
        out.push((format!("w{s}"), win(s), 60.0));
    }
    out.push(("mirror10".into(), mirrored(win(10)), 60.0));
    let mut rev = win(30);
    rev.invert_axis(Axis(0));
    out.push(("rev30".into(), rev.as_standard_layout().to_owned(), 60.0));
    for s in (5..=95).step_by(10) {
        out.push((format!("w{s}"), win(s), 60.0));
    }
    out.push(("mirror50".into(), mirrored(win(50)), 60.0));
    out.push(("scale70".into(), win(70).mapv(|x| x * 1.25), 60.0));
    out.push((
        "sub30_40".into(),
        base.slice(s![40..;2, .., ..]).to_owned(),
        30.0,
    ));
    out
}

fn motion(name: &str, joints: Array3<f32>, fps: f32) -> EvalMotion {
    EvalMotion {
        name: name.into(),
        path: PathBuf::from(name),
        motion: MotionFile::from_joints(fps, SkeletonKind::Smpl24, joints),
        beat_times_s: None,
    }
}

fn input(name: &str, joints: Array3<f32>, fps: f32) -> EvalInput {
    // Beats at 0.25 s + k·0.5 s: frames 15 + 30k at 60 fps, as the script's one-hot.
    let beats = (0..8).map(|k| 0.25 + 0.5 * f64::from(k)).collect();
    EvalInput {
        motion: motion(name, joints, fps),
        beat_times_s: Some(beats),
        song: None,
    }
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .expect("array")
        .iter()
        .map(|x| x.as_f64().expect("number"))
        .collect()
}

/// |got − want| ≤ rel · max(|want|, floor) for every element.
fn assert_close(what: &str, got: &[f64], want: &[f64], rel: f64, floor: f64) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= rel * w.abs().max(floor),
            "{what}[{i}]: got {g}, reference {w}"
        );
    }
}

fn value(v: &Option<SetValue>) -> f64 {
    match v {
        Some(SetValue::Value(x)) => *x,
        other => panic!("expected a value, got {other:?}"),
    }
}

fn plain(v: &SetValue) -> f64 {
    value(&Some(v.clone()))
}

#[test]
fn per_file_metrics_equal_the_reference_code() {
    let want = reference();
    for (name, joints, fps) in cases() {
        let legacy = fps != 60.0;
        let generated = [input(&name, joints, fps)];
        let report = evaluate(&generated, &[], None, &EvalOptions::default()).expect("evaluate");
        let got = &report.generated[0];
        let w = &want["files"][&name];
        // Kinetic features: the reference rounds to float32 (kinetic.py:49) after f64 sums;
        // both sides sum the same f32 differences in a different order, a few f32 ulps.
        assert_close(
            &format!("{name} kinetic"),
            &got.features.kinetic,
            &floats(&w["kinetic"]),
            1e-6,
            1e-6,
        );
        assert_close(
            &format!("{name} kinetic fixed"),
            &got.features.kinetic_fixed_accel,
            &floats(&w["kinetic_fixed_accel"]),
            1e-6,
            1e-6,
        );
        // Geometric features are counts / (T−1): exact unless a relation flips (1/199 ≫ 1e-7).
        assert_close(
            &format!("{name} geometric"),
            &got.features.geometric,
            &floats(&w["geometric"]),
            1e-7,
            1.0,
        );
        if legacy {
            let mut opts = EvalOptions::default();
            opts.legacy_60fps = true;
            let generated = [input(&name, cases().pop().expect("sub30").1, fps)];
            let r = evaluate(&generated, &[], None, &opts).expect("evaluate legacy");
            let f = &r.generated[0].features;
            assert_close(
                "legacy kinetic",
                &f.kinetic,
                &floats(&w["kinetic_legacy"]),
                1e-6,
                1e-6,
            );
            assert_close(
                "legacy geometric",
                &f.geometric,
                &floats(&w["geometric_legacy"]),
                1e-7,
                1.0,
            );
            continue;
        }
        assert_eq!(
            got.motion_beats,
            w["motion_beats_mint"].as_array().map_or(0, Vec::len),
            "{name} beats"
        );
        // BAS: exp of integer distances; the reference's float32 distances round at 1e-7.
        let bas = [
            got.bas_motion_beats.expect("bas"),
            got.bas_music_beats.expect("bas"),
        ];
        let want_bas = [
            w["bas_motion_beats"].as_f64(),
            w["bas_music_beats"].as_f64(),
        ]
        .map(|x| x.expect("bas"));
        assert_close(&format!("{name} bas"), &bas, &want_bas, 1e-6, 1e-6);
        // PFC: EDGE's arithmetic runs in float32 on float32 joints, ours in f64: 1e-6 relative
        // (seen: 6e-8). The skating ratio counts frames: exact.
        assert_close(
            &format!("{name} pfc"),
            &[got.pfc],
            &[w["pfc"].as_f64().expect("pfc")],
            1e-6,
            1e-6,
        );
        assert_close(
            &format!("{name} skate"),
            &[got.skate_ratio],
            &[w["skate_ratio"].as_f64().expect("skate")],
            1e-12,
            1.0,
        );
    }
}

#[test]
fn set_metrics_equal_bailandos_fid_and_diversity() {
    let want = &reference()["sets"]["gen_vs_ref"];
    let all = cases();
    let pick = |n: &str| all.iter().find(|c| c.0 == n).cloned().expect("case");
    let generated: Vec<EvalInput> = GEN
        .iter()
        .map(|n| {
            let (name, j, fps) = pick(n);
            input(&name, j, fps)
        })
        .collect();
    let reference: Vec<EvalMotion> = (5..=95)
        .step_by(10)
        .map(|s| format!("w{s}"))
        .chain(["mirror50".to_string(), "scale70".to_string()])
        .map(|n| {
            let (name, j, fps) = pick(&n);
            motion(&name, j, fps)
        })
        .collect();
    let r = evaluate(&generated, &reference, None, &EvalOptions::default()).expect("evaluate");
    let num = |k: &str| {
        want[k]
            .as_f64()
            .unwrap_or_else(|| want[k]["real"].as_f64().expect(k))
    };
    // FID: the reference z-scores float32 features in float32 and takes scipy's sqrtm of a
    // singular product (8 and 12 samples in 72 / 32 dimensions; scipy warns "might be
    // inaccurate"); seen 6e-8 relative, allowed 1e-6. A dropped term or a wrong normalisation
    // moves FID by whole units.
    let fid = [
        value(&r.set.fid_k),
        value(&r.set.fid_k_fixed_accel),
        value(&r.set.fid_g),
    ];
    let want_fid = ["fid_kinetic", "fid_kinetic_fixed_accel", "fid_geometric"].map(num);
    assert_close("fid", &fid, &want_fid, 1e-6, 1.0);
    // Diversity: mean pairwise distances of the same z-scores, float32 (reference) vs f64:
    // seen 1.3e-7 relative, allowed 1e-6.
    let div = [
        plain(&r.set.div_k),
        plain(&r.set.div_g),
        value(&r.set.div_k_reference),
        value(&r.set.div_g_reference),
    ];
    let want_div = [
        "div_kinetic",
        "div_geometric",
        "div_kinetic_reference",
        "div_geometric_reference",
    ]
    .map(num);
    assert_close("div", &div, &want_div, 1e-6, 1.0);
}
