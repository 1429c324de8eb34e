//! The window stepper (pipeline): one music-to-dance window on its own, seeded by frames known
//! at its start — what live input calls once per hop, with the previous window's tail as seed.

use ndarray::{Array2, Array3, ArrayView2, Axis, s};

use crate::diffusion::noise::NoiseSource;
use crate::diffusion::sampler::{Denoiser, Known, SampleRequest};
use crate::error::{Error, Result};
use crate::package::ModelPackage;
use crate::package::manifest::{Manifest, Role};
use crate::pipelines::dance::{DanceDenoiser, DanceOptions, make_sampler};

/// [`generate_window`] with the package's denoiser.
pub fn generate_package_window(
    package: &mut ModelPackage,
    music: ArrayView2<'_, f32>,
    seed: Option<ArrayView2<'_, f32>>,
    options: &DanceOptions,
    stream: u64,
) -> Result<Array2<f32>> {
    let manifest = package.manifest().clone();
    let mut denoiser = DanceDenoiser::new(package.component(Role::Denoiser)?);
    generate_window(&mut denoiser, &manifest, music, seed, options, stream)
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
        }),
        chain_overlap: 0,
        init: None,
    };
    let mut noise = NoiseSource::new(options.seed, stream);
    let (x, _) = sampler.sample(denoiser, &request, &mut noise, &mut |_, _| {})?;
    Ok(x.index_axis_move(Axis(0), 0))
}
