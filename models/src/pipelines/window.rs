//! The window plan shared by the offline dance ([`crate::generate_dance`]) and live input
//! ([`crate::LiveDance`]): where a window's music starts, how its music is cut from the mel
//! frames with the silence floor past them, and the window stepper — one window on its own,
//! seeded by frames known at its start.

use ndarray::{Array2, Array3, ArrayView2, Axis, s};

use crate::diffusion::noise::NoiseSource;
use crate::diffusion::sampler::{Denoiser, Known, SampleRequest};
use crate::error::{Error, Result};
use crate::package::manifest::{AudioSpec, Manifest};
use crate::pipelines::dance::{DanceOptions, make_sampler};

/// The first mel frame of the music of a window starting at motion frame `frame`:
/// `round(frame / fps · sr / hop)` (EDGE's `start_s · sr / hop`).
pub(crate) fn mel_frame_at(frame: usize, fps: f64, audio: &AudioSpec) -> usize {
    (frame as f64 / fps * audio.frame_rate()).round() as usize
}

/// The music of a window, (music_frames, n_mels) time-major, into `out`: the mel frames from
/// `start` on, clamped at `floor`, where `frames` holds mel frames `first..` time-major; frames
/// it does not hold (past the song's end, not heard yet, forgotten) are `floor`, what silence
/// looks like in this song.
pub(crate) fn cut_music(
    mut out: ndarray::ArrayViewMut2<'_, f32>,
    frames: ArrayView2<'_, f32>,
    first: usize,
    start: usize,
    floor: f32,
) {
    out.fill(floor);
    for (i, mut row) in out.outer_iter_mut().enumerate() {
        let Some(k) = (start + i).checked_sub(first) else {
            continue;
        };
        if k >= frames.nrows() {
            break;
        }
        for (o, v) in row.iter_mut().zip(frames.row(k)) {
            *o = v.max(floor);
        }
    }
}

/// One window on its own (live mode): `music` is (music_frames, n_mels) time-major; `seed` holds
/// up to `window_frames` normalised feature frames known at the window's start (e.g. the
/// previous window's tail). Returns the window's normalised features (window_frames, D);
/// decode with [`crate::decode_features`]. `stream` selects the noise stream for this window.
pub fn generate_window(
    denoiser: &mut dyn Denoiser,
    manifest: &Manifest,
    music: ArrayView2<'_, f32>,
    seed: Option<ArrayView2<'_, f32>>,
    options: &DanceOptions,
    stream: u64,
) -> Result<Array2<f32>> {
    let dance = manifest.dance_spec()?;
    let (w, d) = (dance.window_frames, manifest.motion.dim);
    let a = dance.audio;
    if music.dim() != (a.music_frames, a.n_mels) {
        return Err(Error::Input {
            what: "window music".into(),
            reason: format!(
                "shape {:?}, the package needs ({}, {})",
                music.dim(),
                a.music_frames,
                a.n_mels
            ),
        });
    }
    let sampler = make_sampler(manifest, options)?;
    let mut values = Array3::<f32>::zeros((1, w, d));
    let mut mask = Array3::from_elem((1, w, d), false);
    if let Some(seed) = seed {
        let (k, sd) = seed.dim();
        if k > w || sd != d || seed.iter().any(|v| !v.is_finite()) {
            return Err(Error::Input {
                what: "seed frames".into(),
                reason: format!("shape {:?} must be (<= {w}, {d}) and finite", seed.dim()),
            });
        }
        values.slice_mut(s![0, ..k, ..]).assign(&seed);
        mask.slice_mut(s![0, ..k, ..]).fill(true);
    }
    let music = music.insert_axis(Axis(0));
    let request = SampleRequest {
        music,
        window: (w, d),
        known: seed.map(|_| Known {
            values: values.view(),
            mask: mask.view(),
            exact: true,
        }),
        chain_overlap: 0,
        init: None,
    };
    let mut noise = NoiseSource::new(options.seed, stream);
    let (x, _) = sampler.sample(denoiser, &request, &mut noise, &mut |_, _| {})?;
    Ok(x.index_axis_move(Axis(0), 0))
}
