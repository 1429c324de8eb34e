//! Oracle tests: with one exemplar the optimal denoiser's x0 estimate is that exemplar at every
//! noise level, so every correct sampler must end on it.

use ndarray::{Array3, ArrayView3, s};

use super::*;
use crate::diffusion::schedule::BetaSchedule;
use crate::exemplar::ExemplarDenoiser;

const N: usize = 3;
const T: usize = 16;
const D: usize = 6;
const F: usize = 20;
const M: usize = 8;

fn exemplars(k: usize, seed: u64) -> Array3<f32> {
    let mut src = NoiseSource::new(seed, 99);
    let mut a = Array3::<f32>::zeros((k, T, D));
    a.iter_mut().for_each(|v| *v = src.normal() as f32);
    a
}

fn music() -> Array3<f32> {
    Array3::from_shape_fn((N, F, M), |(n, f, m)| {
        ((n * 7 + f * 3 + m) % 11) as f32 - 60.0
    })
}

fn schedule(kind: BetaSchedule) -> NoiseSchedule {
    match kind {
        BetaSchedule::ScaledLinear => NoiseSchedule::new(kind, 1000, 0.00085, 0.012),
        _ => NoiseSchedule::new(kind, 1000, 1e-4, 0.02),
    }
    .unwrap()
}

fn options(kind: SamplerKind, steps: usize, offset: usize) -> SamplerOptions {
    SamplerOptions {
        kind,
        steps,
        steps_offset: offset,
        ..SamplerOptions::default()
    }
}

fn run(
    sched: NoiseSchedule,
    opts: SamplerOptions,
    ex: Array3<f32>,
    known: Option<Known<'_>>,
    seed: u64,
) -> (Array3<f32>, SampleStats) {
    let mut den = ExemplarDenoiser::new(ex, &sched, opts.prediction, 2.0).unwrap();
    let sampler = Sampler::new(sched, opts).unwrap();
    // Leaked so the request's one lifetime can cover the caller's `known` too (tests only).
    let m: &'static Array3<f32> = Box::leak(Box::new(music()));
    let req = SampleRequest {
        music: m.view(),
        window: (T, D),
        known,
        chain_overlap: 0,
        init: None,
    };
    let mut calls = Vec::new();
    let out = sampler
        .sample(
            &mut den,
            &req,
            &mut NoiseSource::new(seed, 0),
            &mut |d, t| calls.push((d, t)),
        )
        .unwrap();
    assert_eq!(
        calls.last().copied(),
        Some((sampler.timesteps().len(), sampler.timesteps().len()))
    );
    out
}

fn max_err(x: ArrayView3<'_, f32>, e: ArrayView3<'_, f32>) -> f32 {
    let mut m = 0f32;
    for row in x.outer_iter() {
        for (a, b) in row.iter().zip(e.iter()) {
            m = m.max((a - b).abs());
        }
    }
    m
}

/// Exact-recovery tolerance: the last step multiplies x0 by sqrt(alpha_bar_prev) = 1 and adds
/// nothing else, so only f32 rounding of O(1) values through O(1) coefficients remains
/// (~1e-6); 1e-4 leaves margin for the 1/sqrt(alpha_bar) amplification at t = 1..20.
const EXACT: f32 = 1e-4;

#[test]
fn every_exact_sampler_returns_the_single_exemplar() {
    let e = exemplars(1, 1);
    for beta in [
        BetaSchedule::Linear,
        BetaSchedule::ScaledLinear,
        BetaSchedule::Cosine,
    ] {
        for prediction in [Prediction::Epsilon, Prediction::X0] {
            for guidance in [Guidance::Off, Guidance::Single(2.5)] {
                let mut cases = vec![
                    options(SamplerKind::Ddpm, 1000, 0),
                    options(SamplerKind::Ddpm, 100, 0),
                ];
                for eta in [0.0, 1.0] {
                    let mut o = options(SamplerKind::Ddim, 50, 1);
                    o.eta = eta;
                    o.set_alpha_to_one = true;
                    cases.push(o);
                }
                for mut o in cases {
                    o.prediction = prediction;
                    o.guidance = guidance;
                    let label = format!("{beta:?} {o:?}");
                    let (x, stats) = run(schedule(beta), o.clone(), e.clone(), None, 5);
                    let err = max_err(x.view(), e.slice(s![0..1, .., ..]));
                    assert!(err < EXACT, "{label}: max error {err}");
                    let groups = if guidance == Guidance::Off { 1 } else { 2 };
                    assert_eq!(stats.calls, o.steps, "{label}");
                    assert_eq!(
                        stats.rows,
                        o.steps * N * groups,
                        "{label}: one batched call per step"
                    );
                }
            }
        }
    }
}

#[test]
fn ddim_without_alpha_one_ends_one_noise_level_short() {
    // diffusers semantics: with set_alpha_to_one = false the last step lands on alpha_bar_0
    // = 1 - beta_0, i.e. x = sqrt(ab0) e + sqrt(1 - ab0) eps. For eta = 0 eps is the initial
    // noise (|z| < 6 for these 288 normals with probability 1 - 6e-7), so
    // |x - e| <= (1 - sqrt(ab0)) |e| + sqrt(1 - ab0) * 6.
    let e = exemplars(1, 2);
    let sched = schedule(BetaSchedule::Linear);
    let ab0 = sched.alphas_cumprod()[0];
    let emax = e.iter().fold(0f32, |a, b| a.max(b.abs())) as f64;
    let bound = ((1.0 - ab0.sqrt()) * emax + (1.0 - ab0).sqrt() * 6.0) as f32 + EXACT;
    for eta in [0.0, 1.0] {
        let mut o = options(SamplerKind::Ddim, 50, 1);
        o.eta = eta;
        let (x, _) = run(sched.clone(), o, e.clone(), None, 3);
        let err = max_err(x.view(), e.view());
        assert!(err < bound, "eta {eta}: error {err} >= bound {bound}");
        // And it is not the exact x0: the residual noise is there, as in diffusers.
        assert!(err > 1e-4, "eta {eta}: residual noise missing ({err})");
    }
}

#[test]
fn in_painting_keeps_known_frames_and_the_oracle_elsewhere() {
    let e = exemplars(1, 4);
    for kind in [SamplerKind::Ddpm, SamplerKind::Ddim] {
        let x = in_painted(kind, &e, true);
        assert!(
            x.slice(s![.., ..4, ..]).iter().all(|&v| v == 0.25),
            "{kind:?}: known frames"
        );
        let err = max_err(x.slice(s![.., 4.., ..]), e.slice(s![0..1, 4.., ..]));
        assert!(
            err < EXACT,
            "{kind:?}: free frames off the exemplar by {err}"
        );
    }
}

/// The exemplars' oracle sampled with frames 0..4 known as 0.25 (guidance 2, 50 steps), `exact`
/// or guided only.
fn in_painted(kind: SamplerKind, e: &Array3<f32>, exact: bool) -> Array3<f32> {
    let mut values = Array3::<f32>::zeros((N, T, D));
    values.fill(0.25);
    let mut mask = Array3::from_elem((N, T, D), false);
    mask.slice_mut(s![.., ..4, ..]).fill(true);
    let mut o = options(kind, 50, 1);
    o.set_alpha_to_one = true;
    o.guidance = Guidance::Single(2.0);
    let known = Known {
        values: values.view(),
        mask: mask.view(),
        exact,
    };
    run(
        schedule(BetaSchedule::Linear),
        o,
        e.clone(),
        Some(known),
        11,
    )
    .0
}

#[test]
fn seed_frames_select_the_matching_exemplar() {
    // Two exemplars; the first half of exemplar 1 is known. The posterior must put all weight
    // on exemplar 1 by the end, so the free half is exemplar 1's (within EXACT). Stochastic
    // samplers only: replacement in-painting with deterministic DDIM (eta 0) can lock the free
    // half onto the other exemplar early (the harmonisation problem RePaint addresses).
    let e = exemplars(2, 6);
    let mut values = Array3::<f32>::zeros((N, T, D));
    for mut row in values.outer_iter_mut() {
        row.assign(&e.slice(s![1, .., ..]));
    }
    let mut mask = Array3::from_elem((N, T, D), false);
    mask.slice_mut(s![.., ..T / 2, ..]).fill(true);
    for kind in [SamplerKind::Ddpm, SamplerKind::Ddim] {
        let mut o = options(kind, 50, 1);
        o.set_alpha_to_one = true;
        o.eta = 1.0;
        let known = Known {
            values: values.view(),
            mask: mask.view(),
            exact: true,
        };
        let (x, _) = run(
            schedule(BetaSchedule::Linear),
            o,
            e.clone(),
            Some(known),
            13,
        );
        let err = max_err(x.view(), e.slice(s![1..2, .., ..]));
        assert!(err < EXACT, "{kind:?}: {err}");
    }
}

#[test]
fn same_seed_same_output_other_seed_other_output() {
    let e = exemplars(4, 8);
    let mut o = options(SamplerKind::Ddim, 20, 1);
    o.eta = 1.0;
    let sched = schedule(BetaSchedule::Linear);
    let (a, _) = run(sched.clone(), o.clone(), e.clone(), None, 21);
    let (b, _) = run(sched.clone(), o.clone(), e.clone(), None, 21);
    let (c, _) = run(sched, o, e, None, 22);
    assert_eq!(a, b);
    assert_ne!(a, c);
}

/// Wraps a denoiser and checks what the sampler feeds it.
struct Spy<'a> {
    inner: &'a mut dyn Denoiser,
    overlap: usize,
    calls: usize,
    conds: Vec<f32>,
}

impl Denoiser for Spy<'_> {
    fn predict(
        &mut self,
        x_t: ArrayView3<'_, f32>,
        t: &[i64],
        music: ArrayView3<'_, f32>,
        cond: &[f32],
    ) -> Result<Array3<f32>> {
        if self.calls > 0 {
            let n = x_t.dim().0;
            let ov = self.overlap;
            for i in 0..n - 1 {
                assert_eq!(
                    x_t.slice(s![i + 1, ..ov, ..]),
                    x_t.slice(s![i, T - ov.., ..]),
                    "window {} does not continue window {i}",
                    i + 1
                );
            }
        }
        self.calls += 1;
        self.conds = cond.to_vec();
        self.inner.predict(x_t, t, music, cond)
    }
}

#[test]
fn overlapping_windows_share_frames_at_every_step() {
    let e = exemplars(3, 9);
    let sched = schedule(BetaSchedule::Linear);
    let mut den = ExemplarDenoiser::new(e, &sched, Prediction::Epsilon, 0.0).unwrap();
    let mut o = options(SamplerKind::Ddim, 10, 1);
    o.eta = 1.0;
    let sampler = Sampler::new(sched, o).unwrap();
    let m = music();
    let req = SampleRequest {
        music: m.view(),
        window: (T, D),
        known: None,
        chain_overlap: T / 2,
        init: None,
    };
    let mut spy = Spy {
        inner: &mut den,
        overlap: T / 2,
        calls: 0,
        conds: vec![],
    };
    let (x, stats) = sampler
        .sample(&mut spy, &req, &mut NoiseSource::new(1, 0), &mut |_, _| {})
        .unwrap();
    assert_eq!((spy.calls, stats.calls), (10, 10));
    assert_eq!(spy.conds, vec![1.0; N]);
    assert!(x.iter().all(|v| v.is_finite()));
}

#[test]
fn guidance_combines_rows_of_one_call() {
    let mut out = Array3::<f32>::zeros((6, 1, 1));
    // rows: cond (1,2) uncond (0.5, 0.5) style (4, 4) for n = 2
    for (i, v) in [1.0, 2.0, 0.5, 0.5, 4.0, 4.0].into_iter().enumerate() {
        out[[i, 0, 0]] = v;
    }
    let single = Guidance::Single(3.0).combine(out.slice(s![..4, .., ..]).to_owned(), 2);
    assert_eq!(
        single.iter().copied().collect::<Vec<_>>(),
        vec![0.5 + 3.0 * 0.5, 0.5 + 3.0 * 1.5]
    );
    let double = Guidance::Double {
        content: 2.0,
        style: 0.5,
    }
    .combine(out, 2);
    // u + wc (c - u) + ws (cs - c)
    assert_eq!(
        double.iter().copied().collect::<Vec<_>>(),
        vec![0.5 + 2.0 * 0.5 + 0.5 * 3.0, 0.5 + 2.0 * 1.5 + 0.5 * 2.0]
    );
    assert_eq!(
        Guidance::Double {
            content: 1.0,
            style: 1.0
        }
        .cond_codes(),
        &[1.0, 0.0, 2.0]
    );
}

#[test]
fn bad_requests_are_errors_not_panics() {
    let sched = schedule(BetaSchedule::Linear);
    let mut den = ExemplarDenoiser::new(exemplars(1, 1), &sched, Prediction::Epsilon, 0.0).unwrap();
    let sampler = Sampler::new(sched.clone(), options(SamplerKind::Ddim, 5, 1)).unwrap();
    let m = music();
    let too_much = SampleRequest {
        music: m.view(),
        window: (T, D),
        known: None,
        chain_overlap: T,
        init: None,
    };
    assert!(
        sampler
            .sample(
                &mut den,
                &too_much,
                &mut NoiseSource::new(0, 0),
                &mut |_, _| {}
            )
            .is_err()
    );
    let wrong_dim = SampleRequest {
        music: m.view(),
        window: (T, D + 1),
        known: None,
        chain_overlap: 0,
        init: None,
    };
    assert!(
        sampler
            .sample(
                &mut den,
                &wrong_dim,
                &mut NoiseSource::new(0, 0),
                &mut |_, _| {}
            )
            .is_err()
    );
    let mut o = options(SamplerKind::Ddim, 5, 1);
    o.eta = f64::NAN;
    assert!(Sampler::new(sched, o).is_err());
}

#[test]
fn clip_sample_bounds_x0_and_keeps_an_in_range_oracle() {
    // An exemplar inside [-1, 1] is untouched by clipping, so the oracle still holds...
    let e = exemplars(1, 12).mapv(|v| (v * 0.3).clamp(-0.9, 0.9));
    for kind in [SamplerKind::Ddpm, SamplerKind::Ddim] {
        let mut o = options(kind, 50, 1);
        (o.clip_sample, o.set_alpha_to_one) = (true, true);
        let (x, _) = run(schedule(BetaSchedule::Linear), o, e.clone(), None, 2);
        let err = max_err(x.view(), e.view());
        assert!(err < EXACT, "{kind:?}: {err}");
    }
    // ...and one outside it comes back clipped: the final x0 estimate is clamped to [-1, 1].
    let big = exemplars(1, 12).mapv(|v| v * 3.0);
    let mut o = options(SamplerKind::Ddpm, 50, 1);
    (o.clip_sample, o.set_alpha_to_one) = (true, true);
    let (x, _) = run(schedule(BetaSchedule::Linear), o, big.clone(), None, 2);
    assert!(x.iter().all(|v| v.abs() <= 1.0 + EXACT));
    let clipped = big.mapv(|v| v.clamp(-1.0, 1.0));
    assert!(max_err(x.view(), clipped.view()) < EXACT);
}

#[test]
fn guidance_rows_in_one_call_or_one_call_per_group_agree() {
    // The exemplar denoiser treats rows independently, so splitting the batch must give
    // bit-identical results with twice the calls.
    let e = exemplars(3, 14);
    let mut o = options(SamplerKind::Ddim, 10, 1);
    (o.eta, o.guidance) = (1.0, Guidance::Single(2.0));
    let (a, sa) = run(
        schedule(BetaSchedule::Linear),
        o.clone(),
        e.clone(),
        None,
        4,
    );
    o.batch_guidance = false;
    let (b, sb) = run(schedule(BetaSchedule::Linear), o, e, None, 4);
    assert_eq!(a, b);
    assert_eq!((sa.calls, sb.calls), (10, 20));
    assert_eq!(sa.rows, sb.rows);
}

#[test]
fn guiding_known_frames_keeps_what_the_model_made_of_them() {
    // `exact: false` (the dance pipeline's chunk borders): the known frames steer every step
    // but the last, and the result holds the model's own frames there (here the one-exemplar
    // oracle's), not the known values; an in-painting paste would leave 0.25 there.
    let e = exemplars(1, 4);
    for kind in [SamplerKind::Ddpm, SamplerKind::Ddim] {
        let x = in_painted(kind, &e, false);
        let err = max_err(x.view(), e.slice(s![0..1, .., ..]));
        assert!(err < EXACT, "{kind:?}: off the exemplar by {err}");
    }
}
