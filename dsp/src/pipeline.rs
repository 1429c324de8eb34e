//! File → log-mel in one call, decoding on a second thread while the first resamples and
//! computes frames (so compressed formats cost little more than their decoding).

use std::path::Path;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use ndarray::Array2;

use crate::decode::{AudioFileReader, DecodeOptions, DecodeSummary};
use crate::error::{Error, Result};
use crate::mel::MelOptions;
use crate::stream::{FeatureStream, LogMelStream};

/// Per-stage timing of [`load_log_mel`]. Stages overlap (decoding runs on its own thread), so
/// `decode_s + resample_s + mel_s` can exceed `total_s`.
#[non_exhaustive]
#[derive(Debug, Clone, Copy, Default)]
pub struct Stats {
    /// Time spent decoding (excluding waits on the consumer; summed over the two decoder
    /// threads of a split MP3 decode), seconds.
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
    /// The file ended mid-stream: `duration_s` is the audio before the damage
    /// ([`DecodeSummary::truncated`]).
    pub truncated: bool,
    /// Undecodable packets skipped.
    pub bad_packets: usize,
}

/// Decode `path`, resample to `mel.sample_rate`, compute librosa's log-mel `(n_mels, T)`.
///
/// Long MP3s whose header states their length are decoded as two halves on two threads
/// (symphonia's MP3 decoder is the bottleneck there); the second half starts with an accurate
/// seek, whose priming frames restore the decoder state, so the samples equal a serial decode
/// (tested). If that seek fails the file is decoded serially.
///
/// Errors: everything [`crate::decode_file`] reports, and invalid `mel` options.
pub fn load_log_mel(
    path: &Path,
    decode: &DecodeOptions,
    mel: &MelOptions,
) -> Result<(Array2<f32>, Stats)> {
    let t0 = Instant::now();
    if let Some(mid) = mp3_split_point(path, decode)
        && let Some(done) = run(path, decode, mel, Some(mid), t0)?
    {
        return Ok(done);
    }
    run(path, decode, mel, None, t0)?.ok_or_else(|| Error::Corrupt {
        path: path.to_path_buf(),
        reason: "internal: serial decode asked for a retry".into(),
    })
}

/// Shortest MP3 (in frames) worth splitting: ~23 s at 44.1 kHz.
const MIN_SPLIT_FRAMES: u64 = 1 << 20;

fn mp3_split_point(path: &Path, decode: &DecodeOptions) -> Option<u64> {
    if std::thread::available_parallelism().map_or(1, |n| n.get()) < 2 {
        return None;
    }
    let reader = AudioFileReader::open(path, decode).ok()?;
    let frames = reader.mp3_frames()?;
    (frames >= MIN_SPLIT_FRAMES).then_some(frames / 2)
}

/// Second half of a split decode: samples from `mid` on, or `None` when seeking failed.
type SecondHalf = Result<Option<(Vec<f32>, u32, Duration, DecodeSummary)>>;

fn decode_second_half(path: &Path, opts: &DecodeOptions, mid: u64) -> SecondHalf {
    let start = Instant::now();
    let mut reader = AudioFileReader::open(path, opts)?;
    if let Err(e) = reader.seek_to_frame(mid) {
        tracing::debug!(file = %path.display(), error = %e, "split decode: seek failed, decoding serially");
        return Ok(None);
    }
    let mut out = Vec::new();
    let mut rate = 0;
    while let Some(chunk) = reader.next_chunk()? {
        rate = chunk.rate;
        out.extend_from_slice(chunk.samples);
    }
    Ok(Some((out, rate, start.elapsed(), reader.summary())))
}

/// One pass; `Ok(None)` asks the caller to retry without splitting.
fn run(
    path: &Path,
    decode: &DecodeOptions,
    mel: &MelOptions,
    split: Option<u64>,
    t0: Instant,
) -> Result<Option<(Array2<f32>, Stats)>> {
    let mut stream = LogMelStream::new(mel)?;
    let (tx, rx) = mpsc::sync_channel::<(Vec<f32>, u32)>(64);
    let mut consumer_err: Option<Error> = None;
    // The decoder threads log in the caller's span (a daemon job's id and file).
    let span = tracing::Span::current();
    let (first, second) = std::thread::scope(|scope| {
        let second = split.map(|mid| {
            let span = span.clone();
            scope.spawn(move || span.in_scope(|| decode_second_half(path, decode, mid)))
        });
        let first = scope.spawn(move || {
            let _in_job = span.enter();
            let mut waiting = Duration::ZERO;
            let start = Instant::now();
            let res = (|| -> Result<DecodeSummary> {
                let mut reader = AudioFileReader::open(path, decode)?;
                if let Some(mid) = split {
                    reader.stop_after(mid);
                }
                // Batch packets into ~100 ms chunks to keep channel traffic low.
                let mut batch: Vec<f32> = Vec::new();
                let mut batch_rate = 0u32;
                while let Some(chunk) = reader.next_chunk()? {
                    batch.extend_from_slice(chunk.samples);
                    batch_rate = chunk.rate;
                    if batch.len() >= (chunk.rate / 10) as usize {
                        let w = Instant::now();
                        let sent = tx.send((std::mem::take(&mut batch), batch_rate));
                        waiting += w.elapsed();
                        sent.map_err(|_| Error::Cancelled {
                            path: path.to_path_buf(),
                        })?;
                    }
                }
                if !batch.is_empty() {
                    let _ = tx.send((batch, batch_rate));
                }
                Ok(reader.summary())
            })();
            drop(tx);
            (res, start.elapsed().saturating_sub(waiting))
        });
        for (chunk, rate) in rx.iter() {
            if let Err(e) = stream.accept_waveform(rate, &chunk) {
                consumer_err = Some(e);
                break;
            }
        }
        drop(rx);
        (first.join(), second.map(|h| h.join()))
    });
    let panicked = || Error::Corrupt {
        path: path.to_path_buf(),
        reason: "decoder thread panicked".into(),
    };
    let (summary, mut decode_time) = first.map_err(|_| panicked())?;
    if let Some(e) = consumer_err {
        return Err(e);
    }
    let mut summary = summary?;
    if split.is_some_and(|mid| summary.frames != mid) {
        // The header's length was wrong: the halves would not meet. Decode serially.
        return Ok(None);
    }
    if let Some(second) = second {
        let Some((rest, rate, t, tail)) = second.map_err(|_| panicked())?? else {
            return Ok(None);
        };
        decode_time += t;
        summary.truncated |= tail.truncated;
        summary.bad_packets += tail.bad_packets;
        // The halves join seamlessly; feed the second in ~1 s pieces (chunking is irrelevant
        // to the result, see LogMelStream).
        for piece in rest.chunks((rate.max(1)) as usize) {
            stream.accept_waveform(rate, piece)?;
        }
        summary.frames += rest.len() as u64;
    }
    stream.input_finished()?;
    let (resample_s, mel_s) = stream.timings();
    let frames = stream.frames_ready();
    let out = stream.into_log_mel();
    Ok(Some((
        out,
        Stats {
            decode_s: decode_time.as_secs_f64(),
            resample_s,
            mel_s,
            total_s: t0.elapsed().as_secs_f64(),
            frames,
            source_rate: summary.sample_rate,
            source_channels: summary.source_channels,
            duration_s: summary.frames as f64 / f64::from(summary.sample_rate.max(1)),
            truncated: summary.truncated,
            bad_packets: summary.bad_packets,
        },
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The second half of a split MP3 decode equals the serial decode sample for sample, for
    /// split points on and off MP3 frame boundaries.
    #[test]
    fn second_half_equals_serial_tail() {
        let dir = tempfile::tempdir().unwrap();
        let wav = dir.path().join("s.wav");
        let mp3 = dir.path().join("s.mp3");
        let run = |cmd: &str, args: &[&str]| {
            let out = std::process::Command::new(cmd).args(args).output().unwrap();
            assert!(
                out.status.success(),
                "{cmd}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        };
        let (w, m) = (wav.to_str().unwrap(), mp3.to_str().unwrap());
        run(
            "sox",
            &[
                "-n", "-r", "44100", "-c", "2", "-b", "16", w, "synth", "30", "sine", "220-3000",
                "sine", "1250",
            ],
        );
        run(
            "ffmpeg",
            &[
                "-hide_banner",
                "-loglevel",
                "error",
                "-y",
                "-i",
                w,
                "-c:a",
                "libmp3lame",
                m,
            ],
        );
        let serial = crate::decode_file(&mp3, &DecodeOptions::default())
            .unwrap()
            .samples;
        for mid in [500_000u64, 661_500, 1_152 * 600, 1_234_567] {
            let (rest, rate, _, _) = decode_second_half(&mp3, &DecodeOptions::default(), mid)
                .unwrap()
                .unwrap();
            assert_eq!(rate, 44_100);
            assert_eq!(rest.len() as u64 + mid, serial.len() as u64, "mid {mid}");
            assert!(rest == serial[mid as usize..], "mid {mid}: samples differ");
        }
    }
}
