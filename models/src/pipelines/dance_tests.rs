use std::path::Path;

use ndarray::{Array2, Array3, s};

use super::*;
use crate::diffusion::scheduler::Prediction;
use crate::exemplar::ExemplarDenoiser;
use crate::pipelines::window::generate_window;
use crate::test_support::{ANY_SHA, manifest_text};
use choreo_datasets::skeleton::largest_bone_turn_deg;

/// T = 8, stride 4, D = 72, 6 mel frames per window, DDIM 10 steps (see test_support).
fn manifest() -> Manifest {
    Manifest::parse(Path::new("/pkg/tiny"), &manifest_text(ANY_SHA)).unwrap()
}

fn mel(frames: usize) -> Array2<f32> {
    Array2::from_shape_fn((80, frames), |(b, f)| -80.0 + ((b * 3 + f * 7) % 50) as f32)
}

/// Exemplars with period 4 in time, so every window's overlap agrees with its neighbour's.
fn periodic_exemplar() -> Array3<f32> {
    let mut src = NoiseSource::new(3, 5);
    let base: Vec<f32> = (0..4 * 72).map(|_| src.normal() as f32).collect();
    Array3::from_shape_fn((1, 8, 72), |(_, f, d)| base[(f % 4) * 72 + d])
}

fn denoiser(ex: Array3<f32>, m: &Manifest) -> ExemplarDenoiser {
    ExemplarDenoiser::new(ex, &m.schedule().unwrap(), Prediction::Epsilon, 1.0).unwrap()
}

#[test]
fn window_plan_and_output_length() {
    let m = manifest();
    let mut den = denoiser(periodic_exemplar(), &m);
    // 100 mel frames = 99 hops = 3.168 s → round(95.04) = 95 frames at 30 fps.
    let mut seen = Vec::new();
    let dance = generate_dance_with(
        &mut den,
        &m,
        mel(100).view(),
        &DanceOptions::default(),
        &mut |d, t| seen.push((d, t)),
    )
    .unwrap();
    assert_eq!(dance.joints.dim(), (95, 24, 3));
    assert_eq!(dance.fps, 30.0);
    // (95 - 8) / 4 rounded up = 22, plus the first window.
    assert_eq!(dance.stats.windows, 23);
    assert_eq!(
        (
            dance.stats.chunks,
            dance.stats.steps,
            dance.stats.evaluations
        ),
        (1, 10, 10)
    );
    assert_eq!(dance.stats.rows, 230);
    assert_eq!(seen.last().copied(), Some((10, 10)));
    let opts = DanceOptions {
        duration_s: Some(1.0),
        ..DanceOptions::default()
    };
    let dance = generate_dance_with(&mut den, &m, mel(100).view(), &opts, &mut |_, _| {}).unwrap();
    assert_eq!(dance.joints.dim().0, 30);
}

#[test]
fn chunking_keeps_the_oracle_and_every_chunk_size_agrees() {
    // One periodic exemplar: every window must come out as the exemplar, so the stitched
    // features are the exemplar's period tiled, whatever the chunking.
    let m = manifest();
    let ex = periodic_exemplar();
    let mut den = denoiser(ex.clone(), &m);
    let frames = 95;
    let tiled = Array2::from_shape_fn((frames, 72), |(f, d)| ex[[0, f % 4, d]]);
    let expected = decode_features(&m, tiled.view()).unwrap();
    for chunk in [1, 2, 5, 32] {
        let mut progress = Vec::new();
        // The sampler's oracle, before the rigid fit (random exemplars are no skeleton).
        let opts = DanceOptions {
            chunk_windows: chunk,
            rigid_fit: false,
            ..DanceOptions::default()
        };
        let dance = generate_dance_with(&mut den, &m, mel(100).view(), &opts, &mut |d, t| {
            progress.push((d, t))
        })
        .unwrap();
        assert_eq!(dance.stats.chunks, 23usize.div_ceil(chunk));
        assert_eq!(
            progress.last().copied(),
            Some((dance.stats.chunks * 10, dance.stats.chunks * 10))
        );
        // DDIM with set_alpha_to_one = false ends at alpha_bar_0 (see the sampler tests):
        // |x - e| <= (1 - sqrt(0.9999)) |e| + 0.01 |z| with |e|, |z| < 6, and decoding adds a
        // root (sum of two such errors): 2 × (0.0003 + 0.06) ≈ 0.13 per window. In an overlap
        // a frame is one window carrying part of its difference from the other, whose heads
        // are guided, not pasted, at chunk borders: both windows' errors, bound 0.26. The stitcher keeps
        // where each window is and which way it faces, so what agrees is every frame's pose:
        // the frame turned about the vertical through its root (the least-squares turn) and
        // moved onto the oracle's root.
        let mut err = 0f32;
        for f in 0..frames {
            let (got, want) = (
                dance.joints.index_axis(Axis(0), f),
                expected.index_axis(Axis(0), f),
            );
            let centred =
                |p: ArrayView2<'_, f32>, j: usize| [p[[j, 0]] - p[[0, 0]], p[[j, 2]] - p[[0, 2]]];
            let (mut sin, mut cos) = (0f32, 0f32);
            for j in 0..got.dim().0 {
                let (g, w) = (centred(got, j), centred(want, j));
                sin += g[0] * w[1] - g[1] * w[0];
                cos += g[0] * w[0] + g[1] * w[1];
            }
            let (s, c) = sin.atan2(cos).sin_cos();
            for j in 0..got.dim().0 {
                let (g, w) = (centred(got, j), centred(want, j));
                let turned = [c * g[0] - s * g[1], s * g[0] + c * g[1]];
                for (a, b) in [
                    (turned[0], w[0]),
                    (got[[j, 1]], want[[j, 1]]),
                    (turned[1], w[1]),
                ] {
                    err = err.max((a - b).abs());
                }
            }
        }
        assert!(err < 0.26, "chunk {chunk}: {err}");
    }
}

#[test]
fn same_seed_same_dance() {
    let m = manifest();
    let mut src = NoiseSource::new(1, 1);
    let ex = Array3::from_shape_fn((3, 8, 72), |_| src.normal() as f32);
    let mut den = denoiser(ex, &m);
    let run = |den: &mut ExemplarDenoiser, seed| {
        let opts = DanceOptions {
            seed,
            chunk_windows: 4,
            ..DanceOptions::default()
        };
        generate_dance_with(den, &m, mel(80).view(), &opts, &mut |_, _| {})
            .unwrap()
            .joints
    };
    let a = run(&mut den, 9);
    assert_eq!(a, run(&mut den, 9));
    assert_ne!(a, run(&mut den, 10));
    assert!(a.iter().all(|v| v.is_finite()));
}

#[test]
fn music_windows_start_at_the_rounded_mel_frame_and_pad_with_the_floor() {
    let m = manifest();
    let song = mel(20);
    let plan = WindowPlan::new(&m, song.view(), &DanceOptions::default()).unwrap();
    let batch = plan.music_batch(m.dance_spec().unwrap(), m.motion.fps, song.view(), 0, 5);
    assert_eq!(batch.dim(), (5, 6, 80));
    for w in 0..5 {
        // window w starts at w · 4 / 30 s = round(w · 4 / 30 · 31.25) mel frames.
        let start = (w as f64 * 4.0 / 30.0 * 31.25).round() as usize;
        for f in 0..6 {
            for b in [0, 41, 79] {
                let want = if start + f < 20 {
                    song[[b, start + f]]
                } else {
                    -80.0
                };
                assert_eq!(batch[[w, f, b]], want, "window {w} frame {f} band {b}");
            }
        }
    }
}

#[test]
fn a_single_window_keeps_its_seed_frames() {
    let m = manifest();
    let mut src = NoiseSource::new(4, 4);
    let ex = Array3::from_shape_fn((2, 8, 72), |_| src.normal() as f32);
    let mut den = denoiser(ex.clone(), &m);
    let seed = ex.slice(s![1, ..3, ..]).mapv(|v| v + 0.5);
    let music = Array2::<f32>::from_elem((6, 80), -30.0);
    let out = generate_window(
        &mut den,
        &m,
        music.view(),
        Some(seed.view()),
        &DanceOptions::default(),
        0,
    )
    .unwrap();
    assert_eq!(out.dim(), (8, 72));
    assert_eq!(out.slice(s![..3, ..]), seed);
    let wrong = Array2::<f32>::zeros((5, 80));
    assert!(
        generate_window(
            &mut den,
            &m,
            wrong.view(),
            None,
            &DanceOptions::default(),
            0
        )
        .is_err()
    );
}

#[test]
fn decoding_adds_the_root_to_every_offset() {
    let mut m = manifest();
    m.motion.mean = (0..72).map(|i| i as f32).collect();
    m.motion.std = vec![2.0; 72];
    let features = Array2::from_shape_fn((2, 72), |(f, d)| (f + d) as f32 * 0.1);
    let j = decode_features(&m, features.view()).unwrap();
    let v = |f: usize, i: usize| features[[f, i]] * 2.0 + i as f32;
    for f in 0..2 {
        for c in 0..3 {
            assert_eq!(j[[f, 0, c]], v(f, c));
            assert_eq!(j[[f, 5, c]], v(f, c) + v(f, 3 + 3 * 4 + c));
            assert_eq!(j[[f, 23, c]], v(f, c) + v(f, 3 + 3 * 22 + c));
        }
    }
}

#[test]
fn bad_mel_is_a_clear_error() {
    let m = manifest();
    let mut den = denoiser(periodic_exemplar(), &m);
    let mut nan = mel(10);
    nan[[3, 3]] = f32::NAN;
    let cases = [
        (Array2::<f32>::zeros((40, 10)), "bands"),
        (Array2::<f32>::zeros((80, 0)), "no frames"),
        (nan, "NaN"),
    ];
    for (bad, what) in cases {
        let e = generate_dance_with(
            &mut den,
            &m,
            bad.view(),
            &DanceOptions::default(),
            &mut |_, _| {},
        )
        .unwrap_err();
        assert!(e.to_string().contains(what), "{e}");
    }
    let opts = DanceOptions {
        guidance: Some(f32::NAN),
        ..DanceOptions::default()
    };
    let too_many = DanceOptions {
        steps: Some(5000),
        ..DanceOptions::default()
    };
    let e =
        generate_dance_with(&mut den, &m, mel(10).view(), &too_many, &mut |_, _| {}).unwrap_err();
    assert!(
        !e.is_environment() && e.to_string().contains("sampler options"),
        "{e}"
    );
    assert!(generate_dance_with(&mut den, &m, mel(10).view(), &opts, &mut |_, _| {}).is_err());
}

/// A pose (24, 3) with the given bone lengths, every bone pointing along `dir(j)`.
fn pose(root: [f32; 3], lengths: &[f32; 24], dir: impl Fn(usize) -> [f32; 3]) -> Array2<f32> {
    let mut p = Array2::<f32>::zeros((24, 3));
    for c in 0..3 {
        p[[0, c]] = root[c];
    }
    for j in 1..24 {
        let d = dir(j);
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        for c in 0..3 {
            p[[j, c]] = p[[smpl_parent(j), c]] + lengths[j] * d[c] / n;
        }
    }
    p
}

fn bone_length(p: &Array2<f32>, j: usize) -> f32 {
    (0..3)
        .map(|c| (p[[j, c]] - p[[smpl_parent(j), c]]).powi(2))
        .sum::<f32>()
        .sqrt()
}

#[test]
fn a_pose_offset_turns_one_pose_into_the_other_and_fades_out() {
    let lengths: [f32; 24] = std::array::from_fn(|j| 0.05 + 0.01 * j as f32);
    let longer: [f32; 24] = std::array::from_fn(|j| 1.5 * lengths[j]);
    let a = pose([0.0, 1.0, 0.0], &lengths, |j| [1.0, j as f32 * 0.1, 0.0]);
    // b: other directions and longer bones, one bone exactly opposite to a's (j = 5).
    let b = pose([1.0, 0.8, 2.0], &longer, |j| {
        if j == 5 {
            [-1.0, -0.5, 0.0]
        } else {
            [0.0, 1.0, j as f32 * 0.2]
        }
    });
    let offset = PoseOffset::between(a.view(), b.view());
    // Tolerance 1e-5 m: f32 storage of O(1) m positions (ulp 1.2e-7) through 5 chained bones.
    let close = |x: &Array2<f32>, y: &Array2<f32>| (x - y).iter().all(|d| d.abs() < 1e-5);
    assert!(
        close(&offset.apply(b.view(), 1.0), &a),
        "all of the offset: a"
    );
    assert!(close(&offset.apply(b.view(), 0.0), &b), "none of it: b");
    for keep in [0.25f32, 0.5, 0.9] {
        let m = offset.apply(b.view(), keep);
        for c in 0..3 {
            let want = b[[0, c]] + keep * (a[[0, c]] - b[[0, c]]);
            assert!((m[[0, c]] - want).abs() < 1e-5, "root at {keep}");
        }
        for j in 1..24 {
            let want = longer[j] + keep * (lengths[j] - longer[j]);
            assert!(
                (bone_length(&m, j) - want).abs() < 1e-5,
                "bone {j} at {keep}"
            );
            // Each only child is b's turned by `keep` of the angle between b's and a's
            // (siblings turn together: next test).
            if (1..24)
                .filter(|&k| smpl_parent(k) == smpl_parent(j))
                .count()
                > 1
            {
                continue;
            }
            let bone_of = |p: &Array2<f32>| bone(p.view(), j);
            let (to_b, to_a) = (
                angle_between(bone_of(&m), bone_of(&b)),
                angle_between(bone_of(&a), bone_of(&b)),
            );
            assert!((to_b - keep * to_a).abs() < 1e-4, "bone {j} at {keep}");
        }
    }
}

#[test]
fn windows_that_agree_at_one_frame_hand_over_there() {
    // Forearms 40° apart at the overlap's start, meeting at overlap frame 30 and parting again:
    // the hand-over is at frame 30, with nothing to correct, so the output is window a before
    // it and window b from it on, exactly.
    let (window, stride) = (150, 75);
    let meet = stride + 30;
    let a = turning_window(0, window, |_| [1.0, 0.0, 0.0]);
    let b = turning_window(stride, window, |g| {
        in_xy((g as f32 - meet as f32) * 40.0 / 30.0)
    });
    let mut stitcher = Stitcher::new(stride + window, window, stride);
    stitcher.add(0, 2, a.view());
    stitcher.add(1, 2, b.view());
    let out = stitcher.out;
    let close =
        |x: ArrayView3<'_, f32>, y: ArrayView3<'_, f32>| (&x - &y).iter().all(|d| d.abs() < 1e-5);
    assert!(close(
        out.slice(s![..meet, .., ..]),
        a.slice(s![..meet, .., ..])
    ));
    assert!(close(
        out.slice(s![meet.., .., ..]),
        b.slice(s![meet - stride.., .., ..])
    ));
}

#[test]
fn each_chunk_continues_from_the_last_window_of_the_previous_chunk() {
    // Three random exemplars, so windows differ. Windows 0..23 in chunks of 3: at every chunk
    // border the first `overlap` frames of the chunk's first window are guided by the previous
    // window's final tail at every step but the last, as EDGE's copy guides neighbours inside a
    // chunk, so they agree with it as closely as neighbours inside a chunk do, and no closer: a
    // paste of the tail would make the window jump where the pasted frames end (issue 24).
    let m = manifest();
    let mut src = NoiseSource::new(4, 2);
    let ex = Array3::from_shape_fn((3, 8, 72), |_| src.normal() as f32);
    let mut den = denoiser(ex, &m);
    let opts = DanceOptions {
        chunk_windows: 3,
        keep_windows: true,
        ..DanceOptions::default()
    };
    let dance = generate_dance_with(&mut den, &m, mel(100).view(), &opts, &mut |_, _| {}).unwrap();
    let windows = dance.windows.unwrap();
    assert_eq!(windows.dim(), (23, 8, 72));
    let overlap = m.dance_spec().unwrap().overlap_frames();
    let mut gaps: [Vec<f32>; 2] = [Vec::new(), Vec::new()];
    for i in 1..23 {
        let tail = windows.slice(s![i - 1, 8 - overlap.., ..]);
        let head = windows.slice(s![i, ..overlap, ..]);
        let gap = (&head - &tail).iter().fold(0f32, |m, d| m.max(d.abs()));
        gaps[usize::from(i % 3 == 0)].push(gap);
        // Window 0's tail is another window's frames: a chunk seeded from it differs.
        if i >= 2 {
            let first_tail = windows.slice(s![0, 8 - overlap.., ..]);
            assert_ne!(head, first_tail, "window {i}");
        }
    }
    let widest = |g: &[f32]| g.iter().fold(0f32, |m, &v| m.max(v));
    let (inside, border) = (widest(&gaps[0]), widest(&gaps[1]));
    assert!(
        gaps[1].iter().all(|&g| g > 0.0) && border <= 1.5 * inside,
        "chunk borders {:?}, inside chunks at most {inside}",
        gaps[1]
    );
}

#[test]
fn initial_noise_replaces_the_seed_and_must_fit() {
    let m = manifest();
    let mut src = NoiseSource::new(4, 2);
    let ex = Array3::from_shape_fn((3, 8, 72), |_| src.normal() as f32);
    let mut den = denoiser(ex, &m);
    let mut noise = NoiseSource::new(11, 0);
    let init = Array3::from_shape_fn((23, 8, 72), |_| noise.normal() as f32);
    let run = |den: &mut ExemplarDenoiser, seed: u64, init: Option<Array3<f32>>| {
        let opts = DanceOptions {
            seed,
            init_noise: init.map(|a| a.into_dyn()),
            chunk_windows: 5,
            keep_windows: true,
            ..DanceOptions::default()
        };
        generate_dance_with(den, &m, mel(100).view(), &opts, &mut |_, _| {})
    };
    // DDIM eta 0 (the tiny manifest's sampler) with x_T given: the seed no longer matters.
    let a = run(&mut den, 1, Some(init.clone())).unwrap();
    let b = run(&mut den, 2, Some(init.clone())).unwrap();
    assert_eq!(a.windows, b.windows);
    let seeded = run(&mut den, 1, None).unwrap();
    assert_ne!(a.windows, seeded.windows);
    // One window's x_T, (1, T, D) or (T, D), for all equals that x_T repeated.
    let one = init.slice(s![..1, .., ..]).to_owned();
    let repeated = one.broadcast((23, 8, 72)).unwrap().to_owned();
    let c = run(&mut den, 3, Some(one.clone())).unwrap();
    let d = run(&mut den, 4, Some(repeated)).unwrap();
    assert_eq!(c.windows, d.windows);
    let opts = DanceOptions {
        init_noise: Some(one.index_axis(ndarray::Axis(0), 0).to_owned().into_dyn()),
        chunk_windows: 5,
        keep_windows: true,
        ..DanceOptions::default()
    };
    let e = generate_dance_with(&mut den, &m, mel(100).view(), &opts, &mut |_, _| {}).unwrap();
    assert_eq!(c.windows, e.windows);
    let wrong = init.slice(s![..7, .., ..]).to_owned();
    let err = run(&mut den, 1, Some(wrong)).unwrap_err();
    assert!(err.to_string().contains("initial noise"), "{err}");
}

/// `frames` poses from global frame `first` on: fixed bone directions, except the left forearm
/// and hand (bones ending at joints 20 and 22), which point along `forearm(g)` at global frame
/// g; the whole body turns about y by 1° per frame, as a dancer turning.
fn turning_window(first: usize, frames: usize, forearm: impl Fn(usize) -> [f32; 3]) -> Array3<f32> {
    let lengths: [f32; 24] = std::array::from_fn(|j| 0.08 + 0.01 * j as f32);
    let mut out = Array3::<f32>::zeros((frames, 24, 3));
    for f in 0..frames {
        let g = first + f;
        let yaw = (g as f32).to_radians();
        let turn = |d: [f32; 3]| {
            let (s, c) = yaw.sin_cos();
            [c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]]
        };
        let p = pose([0.01 * g as f32, 0.9, 0.0], &lengths, |j| match j {
            20 | 22 => turn(forearm(g)),
            _ => turn([0.3, -1.0 + 0.1 * j as f32, 0.2]),
        });
        out.index_axis_mut(Axis(0), f).assign(&p);
    }
    out
}

/// Unit vector at `deg` degrees from +x toward +y.
fn in_xy(deg: f32) -> [f32; 3] {
    let (s, c) = deg.to_radians().sin_cos();
    [c, s, 0.0]
}

#[test]
fn stitching_windows_whose_forearms_disagree_by_170_degrees_turns_no_bone_abruptly() {
    // Window a's left forearm points along +x; window b's sweeps through the opposite direction
    // during the overlap (from 170° to 190°, 0.27° per frame): the two disagree by 170-180°,
    // as windows 17 and 18 of issue 24's song did. A per-frame slerp between them flips its
    // great circle where b crosses -x and snaps the forearm by ~180° in one frame.
    let (window, stride) = (150, 75);
    let overlap = window - stride;
    let frames = stride + window;
    let sweep = |g: usize| 170.0 + 20.0 * (g as f32 - stride as f32) / (overlap - 1) as f32;
    let a = turning_window(0, window, |_| [1.0, 0.0, 0.0]);
    let b = turning_window(stride, window, |g| in_xy(sweep(g)));
    let mut stitcher = Stitcher::new(frames, window, stride);
    stitcher.add(0, 2, a.view());
    stitcher.add(1, 2, b.view());
    let out = stitcher.out;
    let source = largest_bone_turn_deg(a.view(), &SMPL24_PARENTS)
        .max(largest_bone_turn_deg(b.view(), &SMPL24_PARENTS));
    // The bound the stitcher promises: the windows' own largest turn plus at most 180° spread
    // over the fade (here 74 frames: 2.43°); 1e-3° covers f32 positions.
    let bound = source + 180.0 / (overlap - 1) as f64 + 1e-3;
    let got = largest_bone_turn_deg(out.view(), &SMPL24_PARENTS);
    assert!(
        got <= bound,
        "largest bone turn per frame {got:.2}° > {bound:.2}° (windows' own: {source:.2}°)"
    );
    // Outside the overlap each window as it is; every stitched frame a rigid pose.
    assert_eq!(
        out.slice(s![..stride, .., ..]),
        a.slice(s![..stride, .., ..])
    );
    assert_eq!(
        out.slice(s![window.., .., ..]),
        b.slice(s![overlap.., .., ..])
    );
    let lowest = |p: ArrayView2<'_, f32>| p.column(1).fold(f32::INFINITY, |m, &y| m.min(y));
    for f in stride..window {
        let p = out.index_axis(Axis(0), f).to_owned();
        let floor = lowest(a.index_axis(Axis(0), f)).min(lowest(b.index_axis(Axis(0), f - stride)));
        assert!(
            lowest(p.view()) >= floor - 1e-6,
            "frame {f} below both windows"
        );
        for j in 1..24 {
            let want = bone_length(&a.index_axis(Axis(0), 0).to_owned(), j);
            assert!(
                (bone_length(&p, j) - want).abs() < 1e-5,
                "frame {f} bone {j}"
            );
        }
    }
}

#[test]
fn a_window_danced_elsewhere_is_moved_onto_the_dance_not_slid_there() {
    // Window b is window a's motion (a body turning 1° a frame, walking 1 cm a frame) danced
    // 2 m to the side and 1 m back, as two library clips captured in different places of the
    // room. Fading that displacement over the overlap slides every joint, planted feet
    // included, by 2.2 m / 74 frames = 3 cm a frame; moving b as a whole leaves the motion as
    // danced: the output is window a's motion throughout, continued by b's.
    let (window, stride) = (150, 75);
    let a = turning_window(0, window, |_| [1.0, 0.0, 0.0]);
    let mut b = turning_window(stride, window, |_| [1.0, 0.0, 0.0]);
    b.slice_mut(s![.., .., 0]).mapv_inplace(|x| x + 2.0);
    b.slice_mut(s![.., .., 2]).mapv_inplace(|z| z - 1.0);
    let whole = turning_window(0, stride + window, |_| [1.0, 0.0, 0.0]);
    assert_stitched_into(&a, &b, &whole, stride);
}

#[test]
fn a_window_danced_facing_elsewhere_is_turned_onto_the_dance() {
    // Window b is window a's motion (a body with hips left and right, turning 1° a frame and
    // walking 1 cm a frame) turned 150° about the vertical and danced 2 m away (two library
    // clips captured facing different walls): turned and moved as a whole it continues a's
    // motion exactly. Fading the turn bone by bone, as the stitcher does a pose difference,
    // would bend the pelvis out of shape for half the overlap.
    let (window, stride) = (150, 75);
    let lengths: [f32; 24] = std::array::from_fn(|j| 0.08 + 0.01 * j as f32);
    let body = |first: usize, frames: usize| {
        let mut out = Array3::<f32>::zeros((frames, 24, 3));
        for f in 0..frames {
            let g = first + f;
            let (s, c) = (g as f32).to_radians().sin_cos();
            let turn = |d: [f32; 3]| [c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]];
            let p = pose([0.01 * g as f32, 0.9, 0.0], &lengths, |j| match j {
                1 => turn([1.0, -0.2, 0.0]),
                2 => turn([-1.0, -0.2, 0.0]),
                _ => turn([0.3, -1.0 + 0.1 * j as f32, 0.2]),
            });
            out.index_axis_mut(Axis(0), f).assign(&p);
        }
        out
    };
    let a = body(0, window);
    let mut b = body(stride, window);
    let (s, c) = 150f32.to_radians().sin_cos();
    for mut point in b.lanes_mut(Axis(2)) {
        let (x, z) = (point[0], point[2]);
        point[0] = c * x + s * z + 2.0;
        point[2] = -s * x + c * z;
    }
    let whole = body(0, stride + window);
    assert_stitched_into(&a, &b, &whole, stride);
}

/// Windows a and b (b starting `stride` frames after a), stitched, are `whole` to 1e-5 m (f32
/// positions and rotations of points 2 m away).
fn assert_stitched_into(a: &Array3<f32>, b: &Array3<f32>, whole: &Array3<f32>, stride: usize) {
    let window = a.dim().0;
    let mut stitcher = Stitcher::new(stride + window, window, stride);
    stitcher.add(0, 2, a.view());
    stitcher.add(1, 2, b.view());
    let worst = (&stitcher.out - whole)
        .iter()
        .fold(0f32, |m, d| m.max(d.abs()));
    assert!(
        worst < 1e-5,
        "stitched motion off the danced one by {worst} m"
    );
}

#[test]
fn siblings_turn_together_so_the_pelvis_keeps_its_shape() {
    // b is a's body leaning 80° forward and turned 30°: the same skeleton, so its pelvis
    // (hips and spine from the root) and chest (neck and collars) have a's shapes. Half-way
    // through the offset every angle between sibling bones is still a's; turned one by one
    // about their own axes they would bend the pelvis (issue 24: its rigid fit then moved the
    // hips, and the toes went 6 cm below the floor).
    let lengths: [f32; 24] = std::array::from_fn(|j| 0.08 + 0.01 * j as f32);
    let dir = |j: usize| match j {
        1 => [1.0, -0.3, 0.0],
        2 => [-1.0, -0.3, 0.0],
        3 => [0.0, 1.0, -0.1],
        13 => [1.0, 0.2, 0.0],
        14 => [-1.0, 0.2, 0.0],
        _ => [0.1, if j < 12 { -1.0 } else { 1.0 }, 0.05 * j as f32],
    };
    let (lean, turn) = (80f32.to_radians(), 30f32.to_radians());
    let tilt = |d: [f32; 3]| {
        let (s, c) = lean.sin_cos();
        let d = [d[0], c * d[1] - s * d[2], s * d[1] + c * d[2]];
        let (s, c) = turn.sin_cos();
        [c * d[0] + s * d[2], d[1], -s * d[0] + c * d[2]]
    };
    let a = pose([0.0, 1.0, 0.0], &lengths, dir);
    let b = pose([0.3, 0.7, 0.2], &lengths, |j| tilt(dir(j)));
    let offset = PoseOffset::between(a.view(), b.view());
    for keep in [0.25f32, 0.5, 0.75] {
        let m = offset.apply(b.view(), keep);
        for (x, y) in [(1, 2), (1, 3), (2, 3), (12, 13), (12, 14), (13, 14)] {
            let angle = |p: &Array2<f32>| angle_between(bone(p.view(), x), bone(p.view(), y));
            // 1e-4 rad: f32 directions through one fitted rotation.
            assert!(
                (angle(&m) - angle(&a)).abs() < 1e-4,
                "bones {x}, {y} at {keep}: {} vs {}",
                angle(&m).to_degrees(),
                angle(&a).to_degrees()
            );
        }
    }
}

/// Issue 24: a frame mixed from several poses has shorter legs than the skeleton; its toes on
/// the floor, the rigid fit restores the shins from the hips down and they reach below it.
/// Every fitted frame stays rigid and no lower than its stitched frame.
#[test]
fn the_rigid_fit_puts_no_frame_below_its_stitched_pose() {
    let lengths: [f32; 24] = std::array::from_fn(|j| 0.08 + 0.01 * j as f32);
    let stand = |shin: f32| {
        let mut l = lengths;
        l[7] -= shin;
        l[8] -= shin;
        let mut p = pose([0.0, 0.0, 0.0], &l, |j| match j {
            1 => [1.0, -0.2, 0.0],
            2 => [-1.0, -0.2, 0.0],
            4 | 5 | 7 | 8 => [0.0, -1.0, 0.0],
            10 | 11 => [0.0, -0.3, 1.0],
            _ => [0.05 * j as f32, 1.0, 0.0],
        });
        let low = lowest_joint(p.view());
        p.column_mut(1).mapv_inplace(|y| y - low);
        p
    };
    let mut stitched = Array3::<f32>::zeros((30, 24, 3));
    for f in 0..30 {
        let shrunk = if (10..14).contains(&f) { 0.03 } else { 0.0 };
        stitched.index_axis_mut(Axis(0), f).assign(&stand(shrunk));
    }
    let fitted = rigid_dance(
        &choreo_datasets::SkeletonKind::Smpl24,
        stitched.clone(),
        30.0,
    )
    .unwrap();
    let first = fitted.index_axis(Axis(0), 0).to_owned();
    for f in 0..30 {
        let (got, was) = (
            lowest_joint(fitted.index_axis(Axis(0), f)),
            lowest_joint(stitched.index_axis(Axis(0), f)),
        );
        assert!(
            got >= was - 1e-6,
            "frame {f}: lowest joint {got} below {was}"
        );
        let p = fitted.index_axis(Axis(0), f).to_owned();
        for j in 1..24 {
            assert!(
                (bone_length(&p, j) - bone_length(&first, j)).abs() < 1e-4,
                "frame {f} bone {j} not rigid"
            );
        }
    }
}
