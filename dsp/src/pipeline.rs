//! File → log-mel in one call, decoding on a second thread while the first resamples and
//! computes frames (so compressed formats cost little more than their decoding).

use std::path::Path;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use ndarray::Array2;

use crate::decode::{DecodeOptions, decode_file_with};
use crate::error::{Error, Result};
use crate::mel::MelOptions;
use crate::stream::{FeatureStream, LogMelStream};

/// Per-stage timing of [`load_log_mel`]. Stages overlap (decoding runs on its own thread), so
/// `decode_s + resample_s + mel_s` can exceed `total_s`.
#[non_exhaustive]
#[derive(Debug, Clone, Copy, Default)]
pub struct Stats {
    /// Time the decoder thread spent decoding (excluding waits on the consumer), seconds.
    pub decode_s: f64,
    /// Time spent resampling, seconds.
    pub resample_s: f64,
    /// Time spent computing frames, seconds.
    pub mel_s: f64,
    /// Wall time of the whole call, seconds.
    pub total_s: f64,
    /// Frames produced.
    pub frames: usize,
    /// Source sample rate, Hz.
    pub source_rate: u32,
    /// Source channels.
    pub source_channels: usize,
    /// Decoded duration, seconds.
    pub duration_s: f64,
}

/// Decode `path`, resample to `mel.sample_rate`, compute librosa's log-mel `(n_mels, T)`.
///
/// Errors: everything [`crate::decode_file`] reports, and invalid `mel` options.
pub fn load_log_mel(
    path: &Path,
    decode: &DecodeOptions,
    mel: &MelOptions,
) -> Result<(Array2<f32>, Stats)> {
    let t0 = Instant::now();
    let mut stream = LogMelStream::new(mel)?;
    let (tx, rx) = mpsc::sync_channel::<(Vec<f32>, u32)>(64);
    let opts = decode.clone();
    let owned = path.to_path_buf();
    let mut consumer_err: Option<Error> = None;
    let decoded = std::thread::scope(|scope| {
        let handle = scope.spawn(move || {
            let mut waiting = Duration::ZERO;
            let start = Instant::now();
            // Batch packets into ~100 ms chunks to keep channel traffic low.
            let mut batch: Vec<f32> = Vec::new();
            let mut batch_rate = 0u32;
            let res = decode_file_with(&owned, &opts, |chunk, rate| {
                batch.extend_from_slice(chunk);
                batch_rate = rate;
                if batch.len() >= (rate / 10) as usize {
                    let w = Instant::now();
                    let sent = tx.send((std::mem::take(&mut batch), rate));
                    waiting += w.elapsed();
                    sent.map_err(|_| Error::Cancelled {
                        path: owned.clone(),
                    })?;
                }
                Ok(())
            });
            if res.is_ok() && !batch.is_empty() {
                let _ = tx.send((batch, batch_rate));
            }
            drop(tx);
            (res, start.elapsed().saturating_sub(waiting))
        });
        for (chunk, rate) in rx.iter() {
            if let Err(e) = stream.accept_waveform(rate, &chunk) {
                consumer_err = Some(e);
                break;
            }
        }
        // Dropping the receiver (end of scope of `rx` use) unblocks a waiting decoder.
        drop(rx);
        handle.join()
    });
    let (summary, decode_time) = match decoded {
        Ok(v) => v,
        Err(_) => {
            return Err(Error::Corrupt {
                path: path.to_path_buf(),
                reason: "decoder thread panicked".into(),
            });
        }
    };
    if let Some(e) = consumer_err {
        return Err(e);
    }
    let summary = summary?;
    stream.input_finished()?;
    let (resample_s, mel_s) = stream.timings();
    let frames = stream.frames_ready();
    let out = stream.into_log_mel();
    Ok((
        out,
        Stats {
            decode_s: decode_time.as_secs_f64(),
            resample_s,
            mel_s,
            total_s: t0.elapsed().as_secs_f64(),
            frames,
            source_rate: summary.sample_rate,
            source_channels: summary.source_channels,
            duration_s: summary.frames as f64 / f64::from(summary.sample_rate),
        },
    ))
}
