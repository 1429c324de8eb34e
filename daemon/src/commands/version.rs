//! `choreod --version`

use crate::cli::GlobalArgs;

pub fn run(global: &GlobalArgs) -> anyhow::Result<()> {
    println!("choreod {}", env!("CARGO_PKG_VERSION"));
    let library = choreo_models::locate_library(global.ort_library.as_deref());
    let ort = choreo_models::OrtRuntime::load(&library)?;
    println!(
        "onnxruntime {} ({})",
        ort.version(),
        ort.library().display()
    );
    Ok(())
}
