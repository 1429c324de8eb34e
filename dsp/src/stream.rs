//! The streaming log-mel extractor, shaped like sherpa-onnx's `FeatureExtractor`
//! (`k2-fsa/sherpa-onnx:sherpa-onnx/csrc/features.h`: `AcceptWaveform`, `InputFinished`,
//! `NumFramesReady`, `IsLastFrame`, `GetFrames`).
//!
//! Input at any rate is resampled inside, in fixed blocks ([`crate::StreamResampler`]), keyed by
//! the first rate seen; a later rate change is an error. Frames are computed as soon as their
//! right edge has arrived (centre-padded like librosa: the signal starts after `n_fft / 2`
//! zeros), so any chunking of the input yields bit-identical frames. Memory stays bounded: input
//! older than the next frame is dropped, and the consumer drops frames it has read with
//! [`LogMelStream::discard_frames_before`].
//!
//! top_db: librosa clamps against the maximum of the whole signal, which a stream cannot know.
//! The stream therefore does **not** clamp: its frames are the unclamped `power_to_db` values
//! (bounded below by `10 log10(amin)` = -100 dB anyway). The offline path
//! ([`crate::log_mel`]) runs this stream to the end and then applies the global clamp, so the
//! two agree bit for bit wherever the offline value lies above `max - top_db`.

use ndarray::{Array2, ArrayView2};

use crate::error::{Error, Result};
use crate::mel::{FrameAnalyzer, MelOptions};
use crate::resample::StreamResampler;

/// One streaming feature interface for file and live input (house style item 4).
pub trait FeatureStream {
    /// Feed samples at `sample_rate`. Errors: a rate different from the first call's
    /// ([`Error::SampleRateChanged`]), samples after [`FeatureStream::input_finished`], an
    /// unusable rate. None of them is recoverable for this stream.
    fn accept_waveform(&mut self, sample_rate: u32, samples: &[f32]) -> Result<()>;
    /// No more input: pad the tail with zeros and compute the last frames.
    fn input_finished(&mut self) -> Result<()>;
    /// Frames computed so far (including discarded ones).
    fn frames_ready(&self) -> usize;
    /// Whether `frame` is the final frame (only known after `input_finished`).
    fn is_last_frame(&self, frame: usize) -> bool;
    /// Frames `start..start + n`, time-major `(n, feature_dim)`. Error if any was discarded or
    /// is not ready yet.
    fn frames(&self, start: usize, n: usize) -> Result<ArrayView2<'_, f32>>;
    /// Values per frame (`n_mels`).
    fn feature_dim(&self) -> usize;
}

/// Streaming log-mel extractor (see the module docs for the top_db choice).
#[derive(Debug)]
pub struct LogMelStream {
    analyzer: FrameAnalyzer,
    n_fft: usize,
    hop: usize,
    n_mels: usize,
    resampler: Option<StreamResampler>,
    input_rate: Option<u32>,
    /// Samples of the centre-padded signal from absolute index `buf_start` on.
    buf: Vec<f32>,
    buf_start: usize,
    /// Analysis-rate samples received (not counting the left padding).
    n_samples: usize,
    /// Frames computed so far.
    ready: usize,
    /// Computed frames `held_from..ready`, time-major.
    frames: Vec<f32>,
    held_from: usize,
    finished: bool,
    total: Option<usize>,
    scratch: Vec<f32>,
    resampled: Vec<f32>,
    resample_time: std::time::Duration,
    mel_time: std::time::Duration,
}

impl LogMelStream {
    /// A stream computing `opts` features. Errors: invalid options.
    pub fn new(opts: &MelOptions) -> Result<Self> {
        let analyzer = FrameAnalyzer::new(opts)?;
        let pad = opts.n_fft / 2;
        Ok(Self {
            analyzer,
            n_fft: opts.n_fft,
            hop: opts.hop_length,
            n_mels: opts.n_mels,
            resampler: None,
            input_rate: None,
            buf: vec![0.0; pad],
            buf_start: 0,
            n_samples: 0,
            ready: 0,
            frames: Vec::new(),
            held_from: 0,
            finished: false,
            total: None,
            scratch: vec![0.0; opts.n_fft],
            resampled: Vec::new(),
            resample_time: std::time::Duration::ZERO,
            mel_time: std::time::Duration::ZERO,
        })
    }

    /// The options in use.
    pub fn options(&self) -> &MelOptions {
        self.analyzer.options()
    }

    /// Drop frames before `frame` (already consumed), freeing their memory.
    pub fn discard_frames_before(&mut self, frame: usize) {
        let upto = frame.min(self.ready);
        if upto > self.held_from {
            self.frames.drain(..(upto - self.held_from) * self.n_mels);
            self.held_from = upto;
        }
    }

    /// All frames held, as librosa's `(n_mels, T)` with the global top_db clamp applied.
    /// Meant for the offline path after `input_finished`.
    pub fn into_log_mel(self) -> Array2<f32> {
        let t = self.ready - self.held_from;
        let floor = self
            .analyzer
            .options()
            .top_db
            .map_or(f32::NEG_INFINITY, |top| {
                self.frames
                    .iter()
                    .copied()
                    .fold(f32::NEG_INFINITY, f32::max)
                    - top
            });
        crate::mel::transpose_clamped(&self.frames, t, self.n_mels, floor)
    }

    /// Samples and frame values currently held in memory (for bounded-memory checks).
    pub fn held(&self) -> (usize, usize) {
        (self.buf.len(), self.frames.len())
    }

    /// Seconds spent resampling and computing frames so far.
    pub fn timings(&self) -> (f64, f64) {
        (
            self.resample_time.as_secs_f64(),
            self.mel_time.as_secs_f64(),
        )
    }

    fn push_analysis(&mut self, samples: &[f32]) {
        let t = std::time::Instant::now();
        self.buf.extend_from_slice(samples);
        self.n_samples += samples.len();
        self.compute_frames(false);
        self.mel_time += t.elapsed();
    }

    /// Compute every frame whose samples are available (`at_end`: zeros after the signal).
    fn compute_frames(&mut self, at_end: bool) {
        let pad = self.n_fft / 2;
        let avail_end = pad + self.n_samples; // absolute end of real samples in padded coords
        loop {
            let start = self.ready * self.hop;
            let end = start + self.n_fft;
            if at_end {
                if self.total.is_some_and(|t| self.ready >= t) {
                    break;
                }
            } else if end > avail_end {
                break;
            }
            let lo = start - self.buf_start;
            let have = self.buf.len().saturating_sub(lo).min(self.n_fft);
            if have > 0 {
                self.scratch[..have].copy_from_slice(&self.buf[lo..lo + have]);
            }
            self.scratch[have..].fill(0.0);
            let base = self.frames.len();
            self.frames.resize(base + self.n_mels, 0.0);
            self.analyzer
                .log_mel(&self.scratch, &mut self.frames[base..]);
            self.ready += 1;
        }
        // Drop input no future frame needs.
        let next_start = self.ready * self.hop;
        let drop = next_start
            .saturating_sub(self.buf_start)
            .min(self.buf.len());
        if drop > 0 && (drop >= 4 * self.n_fft || at_end) {
            self.buf.drain(..drop);
            self.buf_start += drop;
        }
    }
}

impl FeatureStream for LogMelStream {
    fn accept_waveform(&mut self, sample_rate: u32, samples: &[f32]) -> Result<()> {
        if self.finished {
            return Err(Error::InputAfterFinish);
        }
        match self.input_rate {
            None => {
                let target = self.analyzer.options().sample_rate;
                if sample_rate != target {
                    self.resampler = Some(StreamResampler::new(sample_rate, target)?);
                } else if sample_rate == 0 {
                    return Err(Error::BadSampleRate {
                        rate: 0,
                        max: crate::decode::MAX_SAMPLE_RATE,
                    });
                }
                self.input_rate = Some(sample_rate);
            }
            Some(r) if r != sample_rate => {
                return Err(Error::SampleRateChanged {
                    expected: r,
                    got: sample_rate,
                });
            }
            Some(_) => {}
        }
        if let Some(rs) = self.resampler.as_mut() {
            let mut out = std::mem::take(&mut self.resampled);
            out.clear();
            let t = std::time::Instant::now();
            rs.push(samples, &mut out)?;
            self.resample_time += t.elapsed();
            self.push_analysis(&out);
            self.resampled = out;
        } else {
            self.push_analysis(samples);
        }
        Ok(())
    }

    fn input_finished(&mut self) -> Result<()> {
        if self.finished {
            return Ok(());
        }
        if let Some(rs) = self.resampler.as_mut() {
            let mut out = Vec::new();
            let t = std::time::Instant::now();
            rs.finish(&mut out)?;
            self.resample_time += t.elapsed();
            self.push_analysis(&out);
        }
        self.finished = true;
        self.total = Some(self.analyzer.options().frame_count(self.n_samples));
        let t = std::time::Instant::now();
        self.compute_frames(true);
        self.mel_time += t.elapsed();
        Ok(())
    }

    fn frames_ready(&self) -> usize {
        self.ready
    }

    fn is_last_frame(&self, frame: usize) -> bool {
        self.total.is_some_and(|t| t > 0 && frame == t - 1)
    }

    fn frames(&self, start: usize, n: usize) -> Result<ArrayView2<'_, f32>> {
        let end = start.saturating_add(n);
        if start < self.held_from || end > self.ready {
            return Err(Error::FramesOutOfRange {
                start,
                end,
                held_from: self.held_from,
                ready: self.ready,
            });
        }
        let a = (start - self.held_from) * self.n_mels;
        let b = (end - self.held_from) * self.n_mels;
        ArrayView2::from_shape((n, self.n_mels), &self.frames[a..b]).map_err(|_| {
            Error::FramesOutOfRange {
                start,
                end,
                held_from: self.held_from,
                ready: self.ready,
            }
        })
    }

    fn feature_dim(&self) -> usize {
        self.n_mels
    }
}
