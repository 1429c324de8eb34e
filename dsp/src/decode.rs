//! Decoding any container/codec symphonia knows into a mono f32 signal at the file's own rate.
//!
//! Everything is bounded by [`DecodeOptions`]: the file size is checked before opening, decoding
//! stops with an error as soon as the decoded duration passes `max_duration_s`, and nothing is
//! allocated from header fields (buffers grow with the samples actually decoded).
//! Encoder delay and padding are trimmed by symphonia's gapless mode (on by default in 0.6:
//! `symphonia-core:src/codecs/audio.rs` `AudioDecoderOptions::gapless`), driven by the
//! container's `Track::delay`/`padding` and per-packet `trim_start`/`trim_end`.

use std::fs::File;
use std::path::Path;

use symphonia::core::codecs::audio::AudioDecoderOptions;
use symphonia::core::codecs::audio::well_known::CODEC_ID_OPUS;
use symphonia::core::errors::Error as SymError;
use symphonia::core::formats::probe::Hint;
use symphonia::core::formats::{FormatOptions, FormatReader, TrackType};
use symphonia::core::io::MediaSourceStream;
use symphonia::core::meta::MetadataOptions;

use crate::error::{Error, Result};

/// Highest input sample rate accepted (768 kHz is the highest rate real hardware/files use).
pub const MAX_SAMPLE_RATE: u32 = 768_000;

/// Limits and knobs for [`decode_file`].
#[non_exhaustive]
#[derive(Debug, Clone)]
pub struct DecodeOptions {
    /// Refuse files bigger than this many bytes (checked before opening). Default: 2 GiB.
    pub max_file_bytes: u64,
    /// Stop with [`Error::TooLong`] once the decoded audio exceeds this many seconds.
    /// Default: 3600 (one hour).
    pub max_duration_s: f64,
    /// Undecodable packets are skipped with a warning; more than this many fail the file.
    /// Default: 32.
    pub max_bad_packets: usize,
}

impl Default for DecodeOptions {
    fn default() -> Self {
        Self { max_file_bytes: 2 << 30, max_duration_s: 3600.0, max_bad_packets: 32 }
    }
}

/// A decoded file: mono samples (channel mean, as librosa's `to_mono`) at the file's own rate.
#[non_exhaustive]
#[derive(Debug, Clone)]
pub struct DecodedAudio {
    /// Mono samples in [-1, 1] (float sources may exceed it).
    pub samples: Vec<f32>,
    /// Sample rate of `samples`, Hz.
    pub sample_rate: u32,
    /// Channel count of the source before mixing.
    pub source_channels: usize,
    /// `samples.len() / sample_rate`, seconds.
    pub duration_s: f64,
}

/// What a streaming decode reports at the end.
#[non_exhaustive]
#[derive(Debug, Clone, Copy)]
pub struct DecodeSummary {
    /// Sample rate, Hz.
    pub sample_rate: u32,
    /// Channels before mixing.
    pub source_channels: usize,
    /// Mono samples delivered.
    pub frames: u64,
    /// Packets skipped as undecodable.
    pub bad_packets: usize,
}

/// Decode `path` completely into memory (mono, native rate).
///
/// Errors: see [`decode_file_with`].
pub fn decode_file(path: &Path, opts: &DecodeOptions) -> Result<DecodedAudio> {
    let mut samples = Vec::new();
    let summary = decode_file_with(path, opts, |chunk, _rate| {
        samples.extend_from_slice(chunk);
        Ok(())
    })?;
    let duration_s = samples.len() as f64 / f64::from(summary.sample_rate);
    Ok(DecodedAudio {
        samples,
        sample_rate: summary.sample_rate,
        source_channels: summary.source_channels,
        duration_s,
    })
}

/// Decode `path`, handing mono chunks (one per decoded packet) to `sink` as they come, so a
/// consumer can compute features while the file is still being decoded.
///
/// Errors (each names the file): empty or too large file, unrecognised container, no audio
/// track, Opus, unsupported codec, too many bad packets, longer than `max_duration_s`, zero
/// samples, a NaN/Inf sample (a float WAV holding NaN/Inf is refused rather than silently
/// zeroed: such a file is corrupt, and zeroing would hide it), a sample-rate change mid-stream,
/// and any error `sink` returns. A file truncated mid-frame decodes up to the damage with a
/// warning (the demuxer's unexpected end of file is the end of the stream).
pub fn decode_file_with(
    path: &Path,
    opts: &DecodeOptions,
    mut sink: impl FnMut(&[f32], u32) -> Result<()>,
) -> Result<DecodeSummary> {
    let p = || path.to_path_buf();
    let meta = std::fs::metadata(path).map_err(|io| Error::Io { path: p(), io })?;
    if meta.len() == 0 {
        return Err(Error::EmptyFile { path: p() });
    }
    if meta.len() > opts.max_file_bytes {
        return Err(Error::FileTooLarge { path: p(), bytes: meta.len(), limit: opts.max_file_bytes });
    }
    let mut hint = Hint::new();
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    if let Some(ext) = &ext {
        hint.with_extension(ext);
    }
    let probe = || -> Result<Box<dyn FormatReader>> {
        let file = File::open(path).map_err(|io| Error::Io { path: p(), io })?;
        let mss = MediaSourceStream::new(Box::new(file), Default::default());
        symphonia::default::get_probe()
            .probe(&hint, mss, FormatOptions::default(), MetadataOptions::default())
            .map_err(|e| match e {
                SymError::IoError(ref io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
                    Error::UnrecognisedFormat { path: p(), reason: "file ends before any audio".into() }
                }
                other => Error::UnrecognisedFormat { path: p(), reason: other.to_string() },
            })
    };
    let mut format = probe()?;
    let track = format.default_track(TrackType::Audio).ok_or_else(|| Error::NoAudioTrack { path: p() })?;
    let track_id = track.id;
    let params = track
        .codec_params
        .as_ref()
        .and_then(|c| c.audio())
        .ok_or_else(|| Error::NoAudioTrack { path: p() })?
        .clone();
    if params.codec == CODEC_ID_OPUS {
        return Err(Error::OpusUnsupported { path: p() });
    }
    let mut decoder = symphonia::default::get_codecs()
        .make_audio_decoder(&params, &AudioDecoderOptions::default())
        .map_err(|e| {
            if ext.as_deref() == Some("opus") {
                Error::OpusUnsupported { path: p() }
            } else {
                Error::UnsupportedCodec { path: p(), reason: e.to_string() }
            }
        })?;

    let mut rate: Option<u32> = None;
    let mut channels = 0usize;
    let mut frames: u64 = 0;
    let mut max_frames: u64 = 0;
    let mut bad_packets = 0usize;
    let mut interleaved: Vec<f32> = Vec::new();
    let mut mono: Vec<f32> = Vec::new();
    loop {
        let packet = match format.next_packet() {
            Ok(Some(packet)) => packet,
            Ok(None) => break,
            Err(SymError::IoError(io)) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
                tracing::warn!(file = %path.display(), "file ends mid-stream (truncated?); using the audio before the damage");
                break;
            }
            Err(SymError::DecodeError(msg)) => {
                bad_packets += 1;
                tracing::warn!(file = %path.display(), error = msg, "skipping malformed data");
                if bad_packets > opts.max_bad_packets {
                    return Err(Error::TooManyBadPackets {
                        path: p(),
                        count: bad_packets,
                        limit: opts.max_bad_packets,
                        last: msg.to_string(),
                    });
                }
                continue;
            }
            Err(e) => return Err(Error::Corrupt { path: p(), reason: e.to_string() }),
        };
        if packet.track_id != track_id {
            continue;
        }
        let buf = match decoder.decode(&packet) {
            Ok(buf) => buf,
            Err(SymError::DecodeError(msg)) => {
                bad_packets += 1;
                tracing::warn!(file = %path.display(), error = msg, "skipping undecodable packet");
                if bad_packets > opts.max_bad_packets {
                    return Err(Error::TooManyBadPackets {
                        path: p(),
                        count: bad_packets,
                        limit: opts.max_bad_packets,
                        last: msg.to_string(),
                    });
                }
                continue;
            }
            Err(SymError::IoError(e)) => {
                bad_packets += 1;
                tracing::warn!(file = %path.display(), error = %e, "skipping truncated packet");
                if bad_packets > opts.max_bad_packets {
                    return Err(Error::TooManyBadPackets {
                        path: p(),
                        count: bad_packets,
                        limit: opts.max_bad_packets,
                        last: e.to_string(),
                    });
                }
                continue;
            }
            Err(e) => return Err(Error::Corrupt { path: p(), reason: e.to_string() }),
        };
        let n = buf.frames();
        if n == 0 {
            continue;
        }
        let spec_rate = buf.spec().rate();
        let ch = buf.spec().channels().count().max(1);
        match rate {
            None => {
                if spec_rate == 0 || spec_rate > MAX_SAMPLE_RATE {
                    return Err(Error::Corrupt {
                        path: p(),
                        reason: format!("sample rate {spec_rate} Hz is outside 1..={MAX_SAMPLE_RATE}"),
                    });
                }
                rate = Some(spec_rate);
                channels = ch;
                // Saturating float->int cast; the product is a bound, not an allocation size.
                max_frames = (opts.max_duration_s.max(0.0) * f64::from(spec_rate)).ceil() as u64;
            }
            Some(r) if r != spec_rate => {
                return Err(Error::Corrupt {
                    path: p(),
                    reason: format!("sample rate changes from {r} Hz to {spec_rate} Hz mid-stream"),
                });
            }
            Some(_) => {}
        }
        if ch != channels {
            return Err(Error::Corrupt {
                path: p(),
                reason: format!("channel count changes from {channels} to {ch} mid-stream"),
            });
        }
        if frames + n as u64 > max_frames {
            return Err(Error::TooLong { path: p(), limit_s: opts.max_duration_s });
        }
        buf.copy_to_vec_interleaved(&mut interleaved);
        mix_to_mono(&interleaved, ch, &mut mono);
        if let Some((i, v)) = mono.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(Error::NonFiniteSample { path: p(), index: frames + i as u64, value: *v });
        }
        frames += n as u64;
        // The rate is set above before any samples reach this point.
        sink(&mono, rate.unwrap_or(spec_rate))?;
    }
    let Some(sample_rate) = rate else {
        return Err(Error::NoSamples { path: p() });
    };
    if frames == 0 {
        return Err(Error::NoSamples { path: p() });
    }
    if bad_packets > 0 {
        tracing::warn!(file = %path.display(), bad_packets, "decoded with skipped packets");
    }
    Ok(DecodeSummary { sample_rate, source_channels: channels, frames, bad_packets })
}

/// Channel mean, in f32 and summed in channel order like numpy's `mean(axis=0)` on float32.
fn mix_to_mono(interleaved: &[f32], channels: usize, out: &mut Vec<f32>) {
    out.clear();
    if channels == 1 {
        out.extend_from_slice(interleaved);
        return;
    }
    let inv = channels as f32;
    out.extend(interleaved.chunks_exact(channels).map(|frame| {
        let sum = frame.iter().fold(0.0f32, |acc, &x| acc + x);
        sum / inv
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mono_mix_is_the_channel_mean() {
        let mut out = Vec::new();
        mix_to_mono(&[1.0, 0.0, 0.5, -0.5, 0.25, 0.75], 2, &mut out);
        assert_eq!(out, vec![0.5, 0.0, 0.5]);
        mix_to_mono(&[0.3, 0.6, 0.9], 3, &mut out);
        assert!((out[0] - 0.6).abs() < 1e-7);
    }
}
