//! Helpers shared by this crate's unit tests.

/// A valid music-to-dance manifest with a small window (T = 8, stride 4, 6 mel frames).
pub(crate) fn manifest_text(sha256: &str) -> String {
    let zeros = vec!["0.0"; 72].join(", ");
    let ones = vec!["1.0"; 72].join(", ");
    format!(
        r#"format = "choreod-model"
format_version = 1
name = "tiny"
description = "unit-test package"
task = "music-to-dance"

[motion]
fps = 30.0
skeleton = "smpl24"
representation = "smpl24-rootpos-rootrel"
dim = 72
window_frames = 8
stride_frames = 4
mean = [{zeros}]
std = [{ones}]

[audio]
sample_rate = 16000
n_fft = 2048
hop = 512
n_mels = 80
fmin = 0.0
fmax = 8000.0
top_db = 80.0
music_frames = 6

[diffusion]
train_steps = 1000
beta_schedule = "linear"
beta_start = 0.0001
beta_end = 0.02
prediction = "epsilon"

[sampler]
kind = "ddim"
steps = 10
eta = 0.0
steps_offset = 1
guidance = 1.0

[components.denoiser]
file = "denoiser.onnx"
sha256 = "{sha256}"
inputs = [
  {{ name = "x_t", dtype = "float32", shape = ["N", 8, 72] }},
  {{ name = "t", dtype = "int64", shape = ["N"] }},
  {{ name = "music", dtype = "float32", shape = ["N", 6, 80] }},
  {{ name = "cond", dtype = "float32", shape = ["N"] }},
]
outputs = [ {{ name = "pred", dtype = "float32", shape = ["N", 8, 72] }} ]
"#
    )
}

/// A sha256 that parses (the file check happens at load, not parse).
pub(crate) const ANY_SHA: &str = "0000000000000000000000000000000000000000000000000000000000000000";
