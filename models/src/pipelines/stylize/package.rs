//! A loaded style-transfer package as the loop's settings ([`style_config`]) and its four ONNX
//! components behind [`StyleNetworks`] ([`stylize_package`]).

use ndarray::{Array2, Array3, ArrayD, ArrayView1, ArrayView2, ArrayView3};

use super::{
    StyleConfig, StyleDenoiserInputs, StyleNetworks, StyleReference, StylizeOptions, Stylized,
    check_spec, input, style_vector, stylize,
};
use crate::error::Result;
use crate::package::ModelPackage;
use crate::package::manifest::{Dim, Role};
use crate::runtime::component::TensorView;

/// The loop's settings from a loaded style-transfer package's manifest.
pub fn style_config(package: &ModelPackage) -> Result<StyleConfig> {
    let m = package.manifest();
    let style = m.style_spec()?;
    Ok(StyleConfig {
        fps: m.motion.fps,
        mean: m.motion.mean.clone(),
        std: m.motion.std.clone(),
        max_frames: style.max_frames,
        min_frames: style.min_frames,
        schedule: m.schedule()?,
        sampler: m.sampler_options(),
        guidance: m.sampler.guidance,
        content_guidance: style.content_guidance,
        style_guidance: style.style_guidance,
        inversion_steps: style.inversion_steps,
    })
}

/// [`stylize`] with a loaded style-transfer package's ONNX components.
pub fn stylize_package(
    package: &mut ModelPackage,
    content: ArrayView2<'_, f32>,
    style: StyleReference<'_>,
    options: &StylizeOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Stylized> {
    let config = style_config(package)?;
    let mut nets = PackageNetworks::new(package);
    stylize(&mut nets, &config, content, style, options, progress)
}

/// The style vector (1, S) of raw HumanML3D features (T, 263) through a style-transfer
/// package's style encoder: what [`stylize_package`] computes for a
/// [`StyleReference::Motion`], so passing it back as a [`StyleReference::Embedding`] gives the
/// same result without running the encoder again.
pub fn encode_style_package(
    package: &mut ModelPackage,
    style: ArrayView2<'_, f32>,
) -> Result<Array2<f32>> {
    let config = style_config(package)?;
    check_spec(&config)?;
    let mut nets = PackageNetworks::new(package);
    style_vector(&mut nets, &config, StyleReference::Motion(style))
}

/// A style-transfer package's components behind [`StyleNetworks`].
struct PackageNetworks<'a> {
    package: &'a mut ModelPackage,
    style_dim: Option<usize>,
}

impl<'a> PackageNetworks<'a> {
    fn new(package: &'a mut ModelPackage) -> Self {
        let style_dim = package
            .manifest()
            .components
            .get(&Role::StyleEncoder)
            .and_then(|c| c.outputs.first())
            .and_then(|o| match o.shape.get(1) {
                Some(Dim::Fixed(s)) => usize::try_from(*s).ok(),
                _ => None,
            });
        Self { package, style_dim }
    }

    fn run(
        &mut self,
        role: Role,
        inputs: &[(&str, TensorView<'_>)],
        output: &str,
    ) -> Result<ArrayD<f32>> {
        self.package.component(role)?.run(inputs)?.take(output)
    }
}

fn rank<D: ndarray::Dimension>(role: &str, a: ArrayD<f32>) -> Result<ndarray::Array<f32, D>> {
    let shape = a.shape().to_vec();
    a.into_dimensionality().map_err(|_| {
        input(
            role,
            format!("output of shape {shape:?} has the wrong rank"),
        )
    })
}

impl StyleNetworks for PackageNetworks<'_> {
    fn encode(
        &mut self,
        features: ArrayView3<'_, f32>,
        mask: ArrayView2<'_, f32>,
    ) -> Result<Array3<f32>> {
        let out = self.run(
            Role::VaeEncoder,
            &[("features", features.into()), ("mask", mask.into())],
            "latent",
        )?;
        rank("vae_encoder", out)
    }

    fn decode(
        &mut self,
        latent: ArrayView3<'_, f32>,
        mask: ArrayView2<'_, f32>,
    ) -> Result<Array3<f32>> {
        let out = self.run(
            Role::VaeDecoder,
            &[("latent", latent.into()), ("mask", mask.into())],
            "features",
        )?;
        rank("vae_decoder", out)
    }

    fn style(
        &mut self,
        features: ArrayView3<'_, f32>,
        mask: ArrayView2<'_, f32>,
    ) -> Result<Array2<f32>> {
        let out = self.run(
            Role::StyleEncoder,
            &[("features", features.into()), ("mask", mask.into())],
            "style",
        )?;
        rank("style_encoder", out)
    }

    fn denoise(&mut self, i: &StyleDenoiserInputs<'_>) -> Result<Array3<f32>> {
        let out = self.run(
            Role::Denoiser,
            &[
                ("x_t", i.x_t.into()),
                ("t", ArrayView1::from(i.t).into()),
                ("content", i.content.into()),
                ("trajectory", i.trajectory.into()),
                ("mask", i.mask.into()),
                ("style", i.style.into()),
            ],
            "pred",
        )?;
        rank("denoiser", out)
    }

    fn finish_batch(&mut self) {
        if let Ok(denoiser) = self.package.component(Role::Denoiser) {
            denoiser.finish_batch();
        }
    }

    fn style_dim(&self) -> Option<usize> {
        self.style_dim
    }
}
