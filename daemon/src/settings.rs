//! The settings layer (ripgrep's HiArgs): where flags ([`crate::cli`]) and the config file
//! (`choreo_config`) become the libraries' options, once. Every verb and the service load ONNX
//! Runtime and model packages through here, and the config's typed values are mapped onto the
//! models crate's types here only.

use std::path::{Path, PathBuf};

use choreo_datasets::ExportOptions;
use choreo_models::{
    DanceOptions, ModelPackage, OrtRuntime, RuntimeOptions, SamplerKind, SongOptions, StyleMode,
    StylizeOptions,
};

/// The kind of package a verb runs, which decides its default.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PackageKind {
    /// Music to dance: `$CHOREOD_MODEL`, else the bundled `library`.
    Dance,
    /// Style transfer: the bundled `style-gaussian`.
    Style,
}

impl PackageKind {
    /// The package directory: `given`, else this kind's default.
    pub fn dir(self, given: Option<&Path>) -> PathBuf {
        if let Some(dir) = given {
            return dir.to_path_buf();
        }
        match self {
            Self::Dance => std::env::var_os("CHOREOD_MODEL")
                .filter(|d| !d.is_empty())
                .map_or_else(|| bundled_package_dir("library"), PathBuf::from),
            Self::Style => bundled_package_dir("style-gaussian"),
        }
    }
}

/// `models/packages/<name>` in the nearest directory above the executable that has it (the
/// checkout it was built in), else that relative path.
fn bundled_package_dir(name: &str) -> PathBuf {
    let relative = Path::new("models").join("packages").join(name);
    std::env::current_exe()
        .ok()
        .iter()
        .flat_map(|e| e.ancestors().skip(1))
        .map(|dir| dir.join(&relative))
        .find(|candidate| candidate.join(choreo_models::MANIFEST_FILE).exists())
        .unwrap_or(relative)
}

/// ONNX Runtime from `configured` (`--ort-library`, the config's `runtime.ort_library`), else
/// `$ORT_DYLIB_PATH`, else the checkout's `.venv`.
pub fn ort(configured: Option<&Path>) -> anyhow::Result<OrtRuntime> {
    Ok(OrtRuntime::load(&choreo_models::locate_library(
        configured,
    ))?)
}

/// Runtime options with `intra_threads` ONNX Runtime threads inside one operator (0: one per
/// CPU this process may use, [`choreo_config::available_cpus`] — ONNX Runtime's own default
/// would count the host's cores, past a container's quota).
pub fn runtime(intra_threads: usize) -> RuntimeOptions {
    let mut runtime = RuntimeOptions::default();
    runtime.intra_threads = match intra_threads {
        0 => choreo_config::available_cpus(),
        n => n,
    };
    runtime
}

/// The deadline of work starting now that may run `seconds` (`--time-limit`,
/// `job.time_limit_s`): ONNX Runtime runs still going then are stopped.
pub fn deadline(seconds: f64) -> choreo_models::Deadline {
    choreo_models::Deadline::after(std::time::Duration::from_secs_f64(seconds))
}

/// The one way a package is loaded: its errors name the package already.
pub fn load_package(
    dir: &Path,
    runtime: &RuntimeOptions,
    ort: &OrtRuntime,
) -> anyhow::Result<ModelPackage> {
    Ok(ModelPackage::load(dir, runtime, ort)?)
}

impl crate::cli::ModelArgs {
    /// ONNX Runtime's options for this run (`--intra-threads`).
    pub fn runtime(&self) -> RuntimeOptions {
        runtime(self.intra_threads)
    }

    /// The package of `--model`, else `kind`'s default, loaded with `runtime`.
    pub fn load(
        &self,
        kind: PackageKind,
        runtime: &RuntimeOptions,
        ort: &OrtRuntime,
    ) -> anyhow::Result<ModelPackage> {
        load_package(&kind.dir(self.model.as_deref()), runtime, ort)
    }
}

impl crate::cli::SamplerArgs {
    /// The dance pipeline's options with this sampler, steps and seed (the rest at their
    /// defaults).
    pub fn dance_options(&self) -> DanceOptions {
        let mut dance = DanceOptions::default();
        dance.seed = self.seed;
        dance.steps = self.steps;
        dance.sampler = self.sampler.map(crate::cli::SamplerArg::kind);
        dance
    }
}

impl crate::cli::OutputArgs {
    /// Refuse, before a long job rather than after it, an output that is one of `inputs` (each
    /// named by its flag), whose folder cannot be written, or whose format cannot hold the
    /// export options; those options.
    pub fn check(&self, inputs: &[(&str, &Path)]) -> anyhow::Result<ExportOptions> {
        crate::commands::refuse_output_over_input(&self.output, "-o", inputs)?;
        crate::commands::check_output_folder(&self.output, "-o")?;
        let export = self.export.options();
        choreo_datasets::check_output(&self.output, &export)?;
        Ok(export)
    }
}

/// The models crate's sampler for the config's.
pub fn sampler(sampler: choreo_config::Sampler) -> SamplerKind {
    match sampler {
        choreo_config::Sampler::Ddim => SamplerKind::Ddim,
        choreo_config::Sampler::Ddpm => SamplerKind::Ddpm,
        choreo_config::Sampler::DpmSolverPlusPlus => SamplerKind::DpmSolverPlusPlus,
    }
}

/// The models crate's style mode for the config's.
pub fn style_mode(mode: choreo_config::StyleMode) -> StyleMode {
    match mode {
        choreo_config::StyleMode::Transfer => StyleMode::Transfer,
        choreo_config::StyleMode::Inversion => StyleMode::Inversion,
    }
}

/// How the service dances every song: `[job]` and `[limits]`.
pub fn song_options(config: &choreo_config::Config) -> SongOptions {
    let mut song = SongOptions::default();
    song.dance.seed = config.job.seed;
    song.dance.steps = config.job.steps;
    song.dance.guidance = config.job.guidance;
    if let Some(chunk) = config.job.chunk_windows {
        song.dance.chunk_windows = chunk;
    }
    song.max_file_bytes = config.limits.max_file_bytes;
    song.max_audio_seconds = config.limits.max_audio_seconds;
    song.min_audio_seconds = config.limits.min_audio_seconds;
    song.fail_truncated = config.limits.fail_truncated_audio;
    song
}

/// How the service's live source runs each session: `[live]` (the output file is set per
/// session; no audio or wall-clock limit: a session runs until the daemon stops).
pub fn live_options(live: &choreo_config::LiveConfig) -> crate::live::LiveOptions {
    let mut dance = DanceOptions::default();
    dance.seed = live.seed;
    dance.sampler = live.sampler.map(sampler);
    crate::live::LiveOptions {
        device: live.device.clone(),
        hop_s: live.hop_s,
        steps: live.steps,
        min_steps: live.min_steps,
        latency_budget: std::time::Duration::from_secs_f64(live.latency_budget_s),
        dance,
        duration_s: None,
        max_wall: None,
        output: None,
        osc: live.osc,
        nice: live.nice,
    }
}

/// How the service stylizes every file of the style inbox: `[style]`.
pub fn stylize_options(style: &choreo_config::StyleConfig) -> StylizeOptions {
    let mut options = StylizeOptions::new(style_mode(style.mode));
    options.guidance = style.guidance;
    options.steps = style.steps;
    options
}

/// The config file `choreod serve` reads, loaded once: before logging starts (its `[log]`
/// section sets the log) and then handed to the service, which reports its errors.
#[derive(Debug)]
pub struct ServeConfig {
    /// Where it was read from.
    pub path: PathBuf,
    /// The validated config, or why it is not one.
    pub config: choreo_config::Result<choreo_config::Config>,
}

impl ServeConfig {
    /// Read and validate the file at `path`.
    pub fn load(path: PathBuf) -> Self {
        let config = choreo_config::load(&path);
        Self { path, config }
    }

    /// The validated config, with the file named in its errors.
    pub fn into_config(self) -> anyhow::Result<(PathBuf, choreo_config::Config)> {
        Ok((self.path, self.config?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_config_spells_samplers_and_style_modes_as_the_models_crate_does() {
        for s in choreo_config::Sampler::ALL {
            assert_eq!(s.as_str(), sampler(s).as_str());
        }
        for m in choreo_config::StyleMode::ALL {
            assert_eq!(m.as_str(), style_mode(m).as_str());
        }
    }
}
