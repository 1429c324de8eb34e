//! What the sampling loop costs outside the network: a 3-minute song through a package's
//! manifest with a denoiser that returns zeros (noise, steps, overlap copies, stitching).
//!
//!     cargo run --release -p choreo-models --example sampler_overhead -- PACKAGE_DIR
use choreo_models::{DanceOptions, Denoiser, Manifest, generate_dance_with};
use ndarray::{Array2, Array3, ArrayView3};

struct Zero;
impl Denoiser for Zero {
    fn predict(
        &mut self,
        x: ArrayView3<'_, f32>,
        _: &[i64],
        _: ArrayView3<'_, f32>,
        _: &[f32],
    ) -> choreo_models::Result<Array3<f32>> {
        Ok(Array3::zeros(x.dim()))
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dir = std::path::PathBuf::from(std::env::args().nth(1).ok_or("PACKAGE")?);
    let m = Manifest::load(&dir)?;
    let mel = Array2::from_elem((80, 5626), -40.0f32);
    for steps in [1, 2, 50] {
        let mut o = DanceOptions::default();
        o.steps = Some(steps);
        let t = std::time::Instant::now();
        let d = generate_dance_with(&mut Zero, &m, mel.view(), &o, &mut |_, _| {})?;
        println!(
            "steps {steps}: {:?} total {:.3}s denoiser {:.3}s",
            d.joints.dim(),
            t.elapsed().as_secs_f64(),
            d.stats.ort_seconds
        );
    }
    Ok(())
}
