use std::path::Path;

use ndarray::{Array2, Array3, ArrayView3};

use super::*;
use crate::diffusion::noise::NoiseSource;
use crate::diffusion::scheduler::Prediction;
use crate::exemplar::ExemplarDenoiser;
use crate::pipelines::dance::generate_dance_with;
use crate::test_support::{ANY_SHA, manifest_text};
use choreo_datasets::skeleton::{SMPL24_PARENTS, largest_bone_turn_deg};

/// T = 8, stride 4, 6 mel frames per window, 30 fps, 31.25 mel frames/s (see test_support).
fn tiny() -> Manifest {
    Manifest::parse(Path::new("/pkg/tiny"), &manifest_text(ANY_SHA)).unwrap()
}

/// The shipped package: W = 150 frames at 30 fps, 157 mel frames at 31.25 frames/s.
fn exemplar() -> Manifest {
    Manifest::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("packages/exemplar")).unwrap()
}

/// A song's log-mel (80, frames) in dB, in [-80, -31] as librosa's top_db = 80 leaves it.
fn song(frames: usize) -> Array2<f32> {
    Array2::from_shape_fn((80, frames), |(b, f)| -80.0 + ((b * 3 + f * 7) % 50) as f32)
}

/// The exemplar denoiser, keeping the music of every batch it denoises.
struct Recording {
    inner: ExemplarDenoiser,
    music: Vec<Array3<f32>>,
    batch_open: bool,
}

impl Recording {
    fn new(m: &Manifest) -> Self {
        let mut src = NoiseSource::new(3, 5);
        let ex = Array3::from_shape_fn((1, 8, 72), |_| src.normal() as f32);
        let inner =
            ExemplarDenoiser::new(ex, &m.schedule().unwrap(), Prediction::Epsilon, 1.0).unwrap();
        Self {
            inner,
            music: Vec::new(),
            batch_open: false,
        }
    }
}

impl Denoiser for Recording {
    fn predict(
        &mut self,
        x_t: ArrayView3<'_, f32>,
        t: &[i64],
        music: ArrayView3<'_, f32>,
        cond: &[f32],
    ) -> Result<Array3<f32>> {
        if !self.batch_open {
            self.music.push(music.to_owned());
            self.batch_open = true;
        }
        self.inner.predict(x_t, t, music, cond)
    }

    fn finish_batch(&mut self) {
        self.batch_open = false;
    }
}

#[test]
fn a_live_dance_fed_a_song_frame_by_frame_makes_the_offline_windows() {
    let m = tiny();
    let mel = song(40);
    // Offline: one window per batch, so the denoiser sees each window's music on its own.
    let mut offline = Recording::new(&m);
    let options = DanceOptions {
        chunk_windows: 1,
        ..DanceOptions::default()
    };
    let dance =
        generate_dance_with(&mut offline, &m, mel.view(), &options, &mut |_, _| {}).unwrap();
    // 39 hops = 1.248 s = 37 frames: windows start at 0, 4, ..., 32.
    assert_eq!(dance.stats.windows, 9);
    assert_eq!(offline.music.len(), 9);

    // Live, with the hop = the offline stride, fed one mel frame at a time.
    let mut live = LiveDance::new(&m, 4).unwrap();
    let mut heard = Recording::new(&m);
    let mut steps = Vec::new();
    for f in 0..mel.ncols() {
        live.push_mel(mel.column(f).to_vec().as_slice()).unwrap();
        while let Some(step) = live.step_with(&mut heard, &options).unwrap() {
            steps.push((step, live.mel_heard()));
        }
    }
    // Ends 4, 8, ..., 40: a window is made once its music is heard (6 mel frames, 0.19 s of
    // the 0.27 s window), so the last, frames 32..40, needs mel frames 33..39 of the 40.
    assert_eq!(steps.len(), 10);
    assert_eq!(live.frames(), 40);
    for (j, (step, _)) in steps.iter().enumerate() {
        assert!(
            step.held.is_none(),
            "window {j}: fed frame by frame, never behind"
        );
        assert_eq!(step.window.end, 4 * (j + 1), "window {j}");
        assert_eq!(
            step.window.start,
            (4 * (j + 1)).saturating_sub(8),
            "window {j}"
        );
        assert_eq!(step.fresh.first, 4 * j);
        assert_eq!(step.fresh.pose.joints.dim(), (4, 24, 3));
    }
    // Once a whole window was heard, live window j is offline window j - 1: the same frames,
    // the same music to the bit.
    for (j, (step, _)) in steps.iter().enumerate().skip(1) {
        let w = step.window;
        assert_eq!(
            w.start,
            (j - 1) * 4,
            "window {j} starts where offline window {} does",
            j - 1
        );
        assert_eq!(
            heard.music[j],
            offline.music[j - 1],
            "live window {j} hears the music of offline window {}",
            j - 1
        );
    }
    // The named difference: the warm-up window (end 4 < W = 8) runs before its music's last
    // frame is heard. Its heard rows are the song's; the rest (here 1 of 6 rows) is the floor
    // of what was heard (running max - top_db), where offline plays the song on.
    let (warm, heard_then) = (&steps[0].0.window, steps[0].1);
    assert_eq!((warm.mel_start, warm.mel_needed), (0, 5));
    assert_eq!(heard_then, 5);
    let running_floor = mel.slice(s![.., ..5]).fold(f32::MIN, |a, &v| a.max(v)) - 80.0;
    for r in 0..6 {
        for b in 0..80 {
            let got = heard.music[0][[0, r, b]];
            if r < warm.mel_needed {
                assert_eq!(got, offline.music[0][[0, r, b]], "row {r} band {b}");
            } else {
                assert_eq!(got, running_floor, "row {r} band {b}");
                assert_ne!(got, offline.music[0][[0, r, b]]);
            }
        }
    }
}

#[test]
fn a_live_dance_that_fell_behind_holds_the_last_pose_and_catches_up() {
    let m = tiny();
    let mel = song(40);
    let mut live = LiveDance::new(&m, 4).unwrap();
    let mut den = Recording::new(&m);
    assert!(
        live.step_with(&mut den, &DanceOptions::default())
            .unwrap()
            .is_none(),
        "nothing heard, nothing made"
    );
    let all: Vec<f32> = mel.t().iter().copied().collect();
    // Mel frames 0..5: the warm-up window, frames 0..4.
    live.push_mel(&all[..5 * 80]).unwrap();
    let step = live
        .step_with(&mut den, &DanceOptions::default())
        .unwrap()
        .unwrap();
    assert!(step.held.is_none());
    assert_eq!(live.frames(), 4);
    // Then the rest at once: the newest heard motion frame is floor(39 / 31.25 · 30) = 37.
    // The window may not catch up (hop 4 = half the window), so frames 4..33 hold the last
    // pose, then 33..37 are made.
    live.push_mel(&all[5 * 80..]).unwrap();
    let step = live
        .step_with(&mut den, &DanceOptions::default())
        .unwrap()
        .unwrap();
    let held = step.held.unwrap();
    assert_eq!((held.first, held.pose.joints.dim().0), (4, 29));
    assert_eq!((step.fresh.first, step.fresh.pose.joints.dim().0), (33, 4));
    assert_eq!(step.window.end, 37);
    assert_eq!(live.frames(), 37);
    assert!(
        live.push_mel(&all[..79]).is_err(),
        "a partial frame is refused"
    );
}

#[test]
fn a_hop_over_half_a_window_is_refused() {
    let m = tiny();
    assert!(LiveDance::new(&m, 4).is_ok());
    assert!(LiveDance::new(&m, 5).is_err());
    assert!(LiveDance::new(&m, 0).is_err());
}

#[test]
fn windows_end_at_the_newest_frame_and_seed_with_the_rest() {
    let m = exemplar();
    let live = LiveDance::new(&m, 15).unwrap();
    // Warm-up: the window starts at 0 and ends at the newest frame.
    let p = live.plan(0, 15).unwrap();
    assert_eq!((p.start, p.end, p.mel_start), (0, 15, 0));
    // 15 frames at 30 fps = 0.5 s = 15.625 mel frames at 31.25 frames/s: frame 16 is the
    // newest frame's own (round(15.625) = 16), so 17 must be heard.
    assert_eq!(p.mel_needed, 17);
    // Steady state: W = 150 frames, new = 15, seed = the 135 emitted before.
    let p = live.plan(300, 15).unwrap();
    assert_eq!((p.start, p.end), (165, 315));
    assert_eq!(p.mel_start, (165.0f64 / 30.0 * 31.25).round() as usize);
    // The music window never asks for more than music_frames.
    assert!(p.mel_needed <= p.mel_start + m.dance_spec().unwrap().audio.music_frames);
    assert_eq!(p.mel_needed, (315.0f64 / 30.0 * 31.25).round() as usize + 1);
}

#[test]
fn heard_mel_is_clamped_at_the_running_floor() {
    let mut h = HeardMel::new(2, 80.0);
    h.push(ArrayView2::from_shape((2, 2), &[-10.0, -95.0, -20.0, -30.0]).unwrap())
        .unwrap();
    assert_eq!(h.floor(), -90.0);
    let w = h.window(1, 3);
    assert_eq!(w.row(0).to_vec(), vec![-20.0, -30.0]);
    // Not heard yet: the floor.
    assert_eq!(w.row(1).to_vec(), vec![-90.0, -90.0]);
    let w = h.window(0, 1);
    assert_eq!(w.row(0).to_vec(), vec![-10.0, -90.0]);
    // Discarded frames no longer count against memory; later ones keep their indices.
    h.discard_before(1);
    assert_eq!(h.len(), 2);
    assert_eq!(h.window(1, 1).row(0).to_vec(), vec![-20.0, -30.0]);
    assert_eq!(h.floor(), -90.0);
}

#[test]
fn emitted_features_keep_the_last_window() {
    let mut e = EmittedFeatures::new(2, 3);
    let a = Array2::from_shape_fn((4, 2), |(t, d)| (t * 10 + d) as f32);
    e.push(a.view());
    assert_eq!(e.len(), 4);
    assert!(e.since(0).is_none());
    assert_eq!(e.since(2).unwrap().row(0).to_vec(), vec![20.0, 21.0]);
    let held = e.hold(2);
    assert_eq!(held.row(1).to_vec(), vec![30.0, 31.0]);
    assert_eq!(e.len(), 6);
    assert_eq!(e.since(5).unwrap().row(0).to_vec(), vec![30.0, 31.0]);
}

/// Two exemplar denoisers taking turns, one window each, each exemplar one pose held still:
/// every window plays another pose than the one its seed ends on (as the `library` package
/// does where no candidate continues it), and no window turns a bone by itself.
struct TakingTurns {
    each: [ExemplarDenoiser; 2],
    /// The two poses (normalised features).
    poses: Array2<f32>,
    turn: usize,
}

impl TakingTurns {
    fn new(m: &Manifest) -> Self {
        let mut src = NoiseSource::new(7, 1);
        let poses = Array2::from_shape_fn((2, 72), |_| src.normal() as f32);
        let exemplar = |k: usize| {
            let ex = Array3::from_shape_fn((1, 8, 72), |(_, _, d)| poses[[k, d]]);
            ExemplarDenoiser::new(ex, &m.schedule().unwrap(), Prediction::Epsilon, 1.0).unwrap()
        };
        Self {
            each: [exemplar(0), exemplar(1)],
            poses,
            turn: 0,
        }
    }
}

impl Denoiser for TakingTurns {
    fn predict(
        &mut self,
        x_t: ArrayView3<'_, f32>,
        t: &[i64],
        music: ArrayView3<'_, f32>,
        cond: &[f32],
    ) -> Result<Array3<f32>> {
        self.each[self.turn % 2].predict(x_t, t, music, cond)
    }

    fn finish_batch(&mut self) {
        self.turn += 1;
    }
}

/// A window whose new frames do not continue its seed is carried on from the last pose shown:
/// each bone's correction (its share of the rotation it has in common with its siblings, then
/// its own, each at most 180°) shrinks by equal steps over the hop, so no bone turns by more
/// than 2 x 180° / 4 frames between two frames here, where handing over at once turns bones by
/// as much as the two poses differ (138° here; the `library` package live: 160° at every 0.5 s
/// hop). Measured: 54.5°. Mutation: new frames shown as generated → fails (140.5°).
#[test]
fn a_window_that_does_not_continue_its_seed_is_carried_on_without_a_jump() {
    let m = tiny();
    let mel = song(40);
    let mut live = LiveDance::new(&m, 4).unwrap();
    let mut den = TakingTurns::new(&m);
    let mut shown = Vec::new();
    for f in 0..mel.ncols() {
        live.push_mel(mel.column(f).to_vec().as_slice()).unwrap();
        while let Some(step) = live.step_with(&mut den, &DanceOptions::default()).unwrap() {
            shown.push(step.fresh.pose.joints);
        }
    }
    assert_eq!(shown.len(), 10);
    let views: Vec<_> = shown.iter().map(|j| j.view()).collect();
    let joints = ndarray::concatenate(Axis(0), &views).unwrap();
    // The two exemplars' poses are far apart: shown as generated, the dance would jump.
    let apart = largest_bone_turn_deg(
        decode_features(&m, den.poses.view()).unwrap().view(),
        &SMPL24_PARENTS,
    );
    assert!(
        apart > 90.0,
        "the exemplars' poses differ by only {apart:.0}°"
    );
    let turn = largest_bone_turn_deg(joints.view(), &SMPL24_PARENTS);
    assert!(
        turn <= 2.0 * 180.0 / 4.0,
        "a bone turned {turn:.1}° between two frames"
    );
}
