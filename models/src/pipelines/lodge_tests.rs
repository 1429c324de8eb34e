//! The LODGE pipeline's pieces against the official code's facts and the numpy reference
//! (models/export/tests/make_lodge_sampler_fixture.py, written from the official code, not from
//! this file; its fixture models/tests/fixtures/lodge/sampler.npz).

use std::path::{Path, PathBuf};

use ndarray::{Array3, ArrayD, Axis};

use super::*;
use crate::package::manifest::Manifest;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn tiny() -> Manifest {
    Manifest::load(&workspace().join("models/packages/lodge-tiny-random")).unwrap()
}

fn fixture() -> std::collections::BTreeMap<String, ArrayD<f32>> {
    choreo_datasets::read_npz(&workspace().join("models/tests/fixtures/lodge/sampler.npz")).unwrap()
}

#[test]
fn windows_follow_the_official_layout_and_the_default_covers_every_frame() {
    // 1300 frames: 5 whole Local windows (tail of 20 dropped), 2 Global windows, the second
    // taking the last 1024 of the 1280 frames; its Local windows read from its own start.
    let p = plan(1300, LodgeCompat::Official).unwrap();
    assert_eq!(p.global_starts, [0, 256]);
    assert_eq!(p.local_starts, [0, 256, 512, 768, 256]);
    assert_eq!((p.music_frames, p.out_frames), (1280, 1280));
    let p = plan(1300, LodgeCompat::Fixed).unwrap();
    assert_eq!(p.global_starts, [0, 512]);
    assert_eq!(p.local_starts, [0, 256, 512, 768, 1024, 1280]);
    assert_eq!((p.music_frames, p.out_frames), (1536, 1300));
    // A short song: one Global window over padded music, two Local windows.
    let p = plan(300, LodgeCompat::Fixed).unwrap();
    assert_eq!(p.global_starts, [0]);
    assert_eq!(p.local_starts, [0, 256]);
    assert_eq!((p.music_frames, p.out_frames), (1024, 300));
    let p = plan(1, LodgeCompat::Fixed).unwrap();
    assert_eq!((p.local_starts.len(), p.out_frames), (1, 1));
    // Exactly 20 minutes is one song; one frame more is refused, as are nothing and short
    // songs in the official mode.
    assert_eq!(
        plan(MAX_FRAMES, LodgeCompat::Fixed)
            .unwrap()
            .local_starts
            .len(),
        141
    );
    for (frames, compat) in [
        (MAX_FRAMES + 1, LodgeCompat::Fixed),
        (0, LodgeCompat::Fixed),
        (1023, LodgeCompat::Official),
    ] {
        let e = plan(frames, compat).unwrap_err().to_string();
        assert!(!e.contains('\n') && e.contains("frames"), "{e}");
    }
}

#[test]
fn keyframe_rows_are_cut_as_the_official_code_cuts_them() {
    // Value = 1000 · window + row, so each row says where it came from.
    let keys = Array3::from_shape_fn((2, 104, 139), |(g, r, _)| (1000 * g + r) as f32);
    let from = |rows: &Array2<f32>| rows.column(0).to_vec();
    // Five Local windows: window 1 = rows 28..52 of the first Global window; window 4 (flag 1)
    // = the previous window's rows 100..104, then rows 80..100 of the second window's tail.
    let rows = keyframe_rows(keys.view(), 5);
    assert_eq!(rows.len(), 5);
    assert_eq!(
        from(&rows[1]),
        (28..52).map(|r| r as f32).collect::<Vec<_>>()
    );
    let want: Vec<f32> = (100..104)
        .map(|r| r as f32)
        .chain((80..100).map(|r| (1000 + r) as f32))
        .collect();
    assert_eq!(from(&rows[4]), want);
    // Eight windows (no partial window): window 4 starts with rows 100..104 of the first
    // window (its last chunk replaced the second's first), then the second's rows 8..28.
    let rows = keyframe_rows(keys.view(), 8);
    let want: Vec<f32> = (100..104)
        .map(|r| r as f32)
        .chain((8..28).map(|r| (1000 + r) as f32))
        .collect();
    assert_eq!(from(&rows[4]), want);
}

#[test]
fn local_guidance_ramps_to_its_cap_over_the_first_half() {
    // np.clip(np.linspace(0, 4, 50), None, 2) (diffusion.py:507).
    let w = ramp_weights([0.0, 4.0], 2.0, 50);
    assert_eq!(w.len(), 50);
    assert_eq!(w[0], 0.0);
    assert_eq!(w[1], (4.0f64 / 49.0) as f32);
    assert_eq!(w[24], (96.0f64 / 49.0) as f32);
    assert!(w[25..].iter().all(|v| *v == 2.0));
}

#[test]
fn alphas_cumprod_are_torchs_float32_values() {
    // torch.cumprod(1 - torch.Tensor(make_beta_schedule("cosine", 1000))) in LODGE's
    // utils.py, as float32 bit patterns (torch 2.15 CPU).
    let schedule = tiny().schedule().unwrap();
    let a = alphas_cumprod_f32(schedule.betas());
    for (t, bits) in [
        (0, 1065352523u32),
        (19, 1065323897),
        (499, 1056758029),
        (500, 1056705737),
        (979, 981374886),
        (999, 824633026),
    ] {
        assert_eq!(a[t].to_bits(), bits, "t = {t}: {}", a[t]);
    }
}

#[test]
fn official_timesteps_are_the_packages_and_other_step_counts_follow_linspace() {
    let m = tiny();
    let spec = m.lodge_spec().unwrap();
    let t = timesteps(&spec, 1000, None);
    assert_eq!(t.len(), 51);
    assert_eq!((t[0], t[1], t[49], t[50]), (999, 979, 19, -1));
    // torch.linspace(-1, 999, 11).int() reversed.
    assert_eq!(
        timesteps(&spec, 1000, Some(10)),
        [999, 899, 799, 699, 599, 499, 399, 299, 199, 99, -1]
    );
}

#[test]
fn constraints_match_the_reference_in_both_modes() {
    // The reference builds them from the same raw keyframe rows in float32 numpy; the copied
    // rows agree to the float32 rounding of the normaliser (the same operations: bit-exact in
    // practice, 1e-6 allowed), the mirrored rows go through rotation matrices and axis-angle
    // (float64 here, float64 + float32 rounding there: 1e-5, the bound).
    let m = tiny();
    let spec = m.lodge_spec().unwrap();
    let f = fixture();
    let rows: Vec<usize> = (0..4)
        .chain(28..36)
        .chain(60..68)
        .chain(156..164)
        .chain(188..196)
        .chain(252..256)
        .collect();
    for (name, compat, windows) in [
        ("official", LodgeCompat::Official, 5),
        ("fixed", LodgeCompat::Fixed, 3),
    ] {
        let keys = &f[&format!("{name}_key_rows")];
        let want = &f[&format!("{name}_constraint_rows")];
        let mask = &f[&format!("{name}_constraint_mask")];
        assert_eq!(mask.shape()[0], windows);
        for k in 0..2 {
            let key = keys.index_axis(Axis(0), k).into_dimensionality().unwrap();
            let c = local_constraint(key, spec.normalizer, 256, compat);
            assert_eq!(
                c.mask.view().into_dyn(),
                mask.index_axis(Axis(0), if k == 0 { 0 } else { windows - 1 }),
                "{name} mask"
            );
            for (i, &r) in rows.iter().enumerate() {
                let mirrored = (60..68).contains(&r) || (188..196).contains(&r);
                let tol = if mirrored { 1e-5 } else { 1e-6 };
                for col in (0..4).chain(7..139) {
                    let (got, exp) = (c.value[[r, col]], want[[k, i, col]]);
                    assert!(
                        (got - exp).abs() <= tol,
                        "{name} window {k} row {r} column {col}: {got} vs {exp}"
                    );
                }
            }
        }
    }
}
