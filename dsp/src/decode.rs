//! Decoding any container/codec symphonia knows into a mono f32 signal at the file's own rate.
//!
//! Everything is bounded by [`DecodeOptions`]: the file size is checked before opening, decoding
//! stops with an error as soon as the decoded duration passes `max_duration_s`, and nothing is
//! allocated from header fields (buffers grow with the samples actually decoded).
//! Encoder delay and padding are trimmed by symphonia's gapless mode (on by default in 0.6:
//! `symphonia-core:src/codecs/audio.rs` `AudioDecoderOptions::gapless`), driven by the
//! container's `Track::delay`/`padding` and per-packet `trim_start`/`trim_end`.

use std::fs::File;
use std::path::{Path, PathBuf};

use symphonia::core::codecs::audio::well_known::{CODEC_ID_AAC, CODEC_ID_MP3, CODEC_ID_OPUS};
use symphonia::core::codecs::audio::{AudioDecoder, AudioDecoderOptions};
use symphonia::core::errors::Error as SymError;
use symphonia::core::formats::probe::Hint;
use symphonia::core::formats::{FormatOptions, FormatReader, SeekMode, SeekTo, TrackType};
use symphonia::core::io::MediaSourceStream;
use symphonia::core::meta::MetadataOptions;

use crate::error::{Error, Result};

/// Frames decoded and dropped before a split point (four MP3 frames of 1152).
pub(crate) const SEEK_PREROLL: u64 = 4 * 1152;

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
        Self {
            max_file_bytes: 2 << 30,
            max_duration_s: 3600.0,
            max_bad_packets: 32,
        }
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
    /// Packets skipped as undecodable ([`DecodeSummary::bad_packets`]).
    pub bad_packets: usize,
    /// The file ended mid-stream: `samples` are the audio before the damage
    /// ([`DecodeSummary::truncated`]).
    pub truncated: bool,
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
    /// The file ended mid-stream (a cut download or copy): `frames` are the audio before the
    /// damage, not the whole song.
    pub truncated: bool,
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
        bad_packets: summary.bad_packets,
        truncated: summary.truncated,
    })
}

/// Decode `path`, handing mono chunks (one per decoded packet) to `sink` as they come, so a
/// consumer can compute features while the file is still being decoded.
///
/// Errors: those of [`AudioFileReader`], and any error `sink` returns.
pub fn decode_file_with(
    path: &Path,
    opts: &DecodeOptions,
    mut sink: impl FnMut(&[f32], u32) -> Result<()>,
) -> Result<DecodeSummary> {
    let mut reader = AudioFileReader::open(path, opts)?;
    while let Some(chunk) = reader.next_chunk()? {
        let rate = chunk.rate;
        sink(chunk.samples, rate)?;
    }
    Ok(reader.summary())
}

/// One decoded packet, mixed to mono.
#[derive(Debug)]
pub struct Chunk<'a> {
    /// Mono samples.
    pub samples: &'a [f32],
    /// Their sample rate, Hz.
    pub rate: u32,
}

/// Pull-based decoder of one file: [`AudioFileReader::next_chunk`] until `Ok(None)`.
///
/// Error contract (each error names the file): opening fails for an empty or too large file,
/// an unrecognised container, no audio track, Opus, an unsupported codec. `next_chunk` fails,
/// unrecoverably for this file, after more than `max_bad_packets` undecodable packets (each
/// skipped one is a warning), when the audio passes `max_duration_s`, on a NaN/Inf sample (a
/// float WAV holding NaN/Inf is refused rather than silently zeroed: such a file is corrupt, and
/// zeroing would hide it), on a sample-rate or channel-count change, and at the end of a file
/// that held no samples. A file truncated mid-frame ends early with a warning (the demuxer's
/// unexpected end of file is the end of the stream).
pub struct AudioFileReader {
    path: PathBuf,
    opts: DecodeOptions,
    format: Box<dyn FormatReader>,
    decoder: Box<dyn AudioDecoder>,
    track_id: u32,
    edit: Option<crate::mp4::EditTrim>,
    skip_left: Option<u64>,
    keep_left: Option<u64>,
    rate: Option<u32>,
    channels: usize,
    frames: u64,
    max_frames: u64,
    bad_packets: usize,
    truncated: bool,
    interleaved: Vec<f32>,
    mono: Vec<f32>,
    done: bool,
    /// After a seek: drop output before this timestamp.
    drop_until: Option<i64>,
    /// End of stream after this many output frames (see `stop_after`).
    stop_at: Option<u64>,
    is_mp3: bool,
    num_frames: Option<u64>,
}

impl std::fmt::Debug for AudioFileReader {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AudioFileReader")
            .field("path", &self.path)
            .field("rate", &self.rate)
            .field("channels", &self.channels)
            .field("frames", &self.frames)
            .finish_non_exhaustive()
    }
}

impl AudioFileReader {
    /// Check the size, probe the container and set up the decoder (nothing is decoded yet).
    pub fn open(path: &Path, opts: &DecodeOptions) -> Result<Self> {
        let p = || path.to_path_buf();
        let meta = std::fs::metadata(path).map_err(|io| Error::Io { path: p(), io })?;
        if meta.len() == 0 {
            return Err(Error::EmptyFile { path: p() });
        }
        if meta.len() > opts.max_file_bytes {
            return Err(Error::FileTooLarge {
                path: p(),
                bytes: meta.len(),
                limit: opts.max_file_bytes,
            });
        }
        let mut hint = Hint::new();
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if let Some(ext) = &ext {
            hint.with_extension(ext);
        }
        let file = File::open(path).map_err(|io| Error::Io { path: p(), io })?;
        let mss = MediaSourceStream::new(Box::new(file), Default::default());
        let format = symphonia::default::get_probe()
            .probe(
                &hint,
                mss,
                FormatOptions::default(),
                MetadataOptions::default(),
            )
            .map_err(|e| match e {
                SymError::IoError(ref io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
                    Error::Truncated { path: p() }
                }
                other => Error::UnrecognisedFormat {
                    path: p(),
                    reason: other.to_string(),
                },
            })?;
        let track = format
            .default_track(TrackType::Audio)
            .ok_or_else(|| Error::NoAudioTrack { path: p() })?;
        let track_id = track.id;
        let has_delay = track.delay.is_some();
        let num_frames = track.num_frames;
        let params = track
            .codec_params
            .as_ref()
            .and_then(|c| c.audio())
            .ok_or_else(|| Error::NoAudioTrack { path: p() })?
            .clone();
        if params.codec == CODEC_ID_OPUS {
            return Err(Error::OpusUnsupported { path: p() });
        }
        let decoder = symphonia::default::get_codecs()
            .make_audio_decoder(&params, &AudioDecoderOptions::default())
            .map_err(|e| {
                if ext.as_deref() == Some("opus") {
                    Error::OpusUnsupported { path: p() }
                } else {
                    Error::UnsupportedCodec {
                        path: p(),
                        reason: e.to_string(),
                    }
                }
            })?;
        // AAC in MP4: symphonia leaves the edit list unapplied; apply it here (see mp4.rs).
        let edit = if params.codec == CODEC_ID_AAC && !has_delay {
            crate::mp4::audio_edit_trim(path)
        } else {
            None
        };
        Ok(Self {
            path: p(),
            opts: opts.clone(),
            format,
            decoder,
            track_id,
            edit,
            skip_left: None,
            keep_left: None,
            rate: None,
            channels: 0,
            frames: 0,
            max_frames: 0,
            bad_packets: 0,
            truncated: false,
            interleaved: Vec::new(),
            mono: Vec::new(),
            done: false,
            drop_until: None,
            stop_at: None,
            is_mp3: params.codec == CODEC_ID_MP3,
            num_frames,
        })
    }

    /// Playable frames of an MP3 whose header states them (Xing/LAME), for splitting the decode.
    pub(crate) fn mp3_frames(&self) -> Option<u64> {
        if self.is_mp3 { self.num_frames } else { None }
    }

    /// Seek so that the next chunk starts exactly at output frame `frame`. The seek lands
    /// [`SEEK_PREROLL`] frames earlier and that output is dropped: symphonia's accurate MP3 seek
    /// primes the bit reservoir, but the first granule after it still differs from a continuous
    /// decode (measured: up to ~400 samples), so the decoder needs history of its own.
    pub(crate) fn seek_to_frame(&mut self, frame: u64) -> Result<()> {
        let ts = i64::try_from(frame.saturating_sub(SEEK_PREROLL)).unwrap_or(i64::MAX);
        let seeked = self
            .format
            .seek(
                SeekMode::Accurate,
                SeekTo::Timestamp {
                    ts: ts.into(),
                    track_id: self.track_id,
                },
            )
            .map_err(|e| Error::Corrupt {
                path: self.path.clone(),
                reason: format!("seek to frame {frame}: {e}"),
            })?;
        self.decoder.reset();
        // Output from here is exact only after the preroll: drop up to `frame` ourselves.
        self.drop_until = Some(
            seeked
                .required_ts
                .get()
                .max(i64::try_from(frame).unwrap_or(i64::MAX)),
        );
        self.frames = frame;
        Ok(())
    }

    /// End the stream once `total` output frames (counting from the file start) were delivered.
    pub(crate) fn stop_after(&mut self, total: u64) {
        self.stop_at = Some(total);
    }

    /// Sample rate, known once the first chunk is decoded.
    pub fn sample_rate(&self) -> Option<u32> {
        self.rate
    }

    /// Totals so far (complete after `next_chunk` returned `Ok(None)`).
    pub fn summary(&self) -> DecodeSummary {
        DecodeSummary {
            sample_rate: self.rate.unwrap_or(0),
            source_channels: self.channels,
            frames: self.frames,
            bad_packets: self.bad_packets,
            truncated: self.truncated,
        }
    }

    fn bad_packet(&mut self, what: &str, msg: String) -> Result<()> {
        self.bad_packets += 1;
        tracing::warn!(file = %self.path.display(), error = %msg, "skipping {what}");
        if self.bad_packets > self.opts.max_bad_packets {
            return Err(Error::TooManyBadPackets {
                path: self.path.clone(),
                count: self.bad_packets,
                limit: self.opts.max_bad_packets,
                last: msg,
            });
        }
        Ok(())
    }

    /// The next packet's samples, mono; `Ok(None)` at the end of the stream.
    pub fn next_chunk(&mut self) -> Result<Option<Chunk<'_>>> {
        loop {
            if self.done {
                return Ok(None);
            }
            let packet = match self.format.next_packet() {
                Ok(Some(packet)) => packet,
                Ok(None) => return self.finish(),
                Err(SymError::IoError(io)) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
                    self.truncated = true;
                    return self.finish();
                }
                Err(SymError::DecodeError(msg)) => {
                    self.bad_packet("malformed data", msg.to_string())?;
                    continue;
                }
                Err(e) => {
                    return Err(Error::Corrupt {
                        path: self.path.clone(),
                        reason: e.to_string(),
                    });
                }
            };
            if packet.track_id != self.track_id {
                continue;
            }
            let pts = packet.pts.get();
            let (n, spec_rate, ch) = match self.decoder.decode(&packet) {
                Ok(buf) => {
                    let n = buf.frames();
                    let spec_rate = buf.spec().rate();
                    let ch = buf.spec().channels().count().max(1);
                    buf.copy_to_vec_interleaved(&mut self.interleaved);
                    (n, spec_rate, ch)
                }
                Err(SymError::DecodeError(msg)) => {
                    self.bad_packet("undecodable packet", msg.to_string())?;
                    continue;
                }
                Err(SymError::IoError(e)) => {
                    self.bad_packet("truncated packet", e.to_string())?;
                    continue;
                }
                Err(e) => {
                    return Err(Error::Corrupt {
                        path: self.path.clone(),
                        reason: e.to_string(),
                    });
                }
            };
            if n == 0 {
                continue;
            }
            self.check_spec(spec_rate, ch)?;
            if self.frames + n as u64 > self.max_frames {
                return Err(Error::TooLong {
                    path: self.path.clone(),
                    limit_s: self.opts.max_duration_s,
                });
            }
            mix_to_mono(&self.interleaved, ch, &mut self.mono);
            self.apply_edit(spec_rate);
            if let Some(req) = self.drop_until {
                let skip = usize::try_from(req.saturating_sub(pts).max(0)).unwrap_or(usize::MAX);
                let skip = skip.min(self.mono.len());
                self.mono.drain(..skip);
                if !self.mono.is_empty() {
                    self.drop_until = None;
                }
            }
            if let Some(stop) = self.stop_at {
                let left = stop.saturating_sub(self.frames);
                self.mono
                    .truncate(usize::try_from(left).unwrap_or(usize::MAX));
                if left == 0 {
                    return self.finish();
                }
            }
            if self.mono.is_empty() {
                continue;
            }
            if let Some((i, v)) = self.mono.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(Error::NonFiniteSample {
                    path: self.path.clone(),
                    index: self.frames + i as u64,
                    value: *v,
                });
            }
            self.frames += self.mono.len() as u64;
            return Ok(Some(Chunk {
                samples: &self.mono,
                rate: spec_rate,
            }));
        }
    }

    fn finish(&mut self) -> Result<Option<Chunk<'_>>> {
        self.done = true;
        if self.frames == 0 {
            return Err(Error::NoSamples {
                path: self.path.clone(),
            });
        }
        if self.truncated {
            let seconds = self.frames as f64 / f64::from(self.rate.unwrap_or(1).max(1));
            tracing::warn!(file = %self.path.display(), "the file ends mid-stream (truncated?): using the {seconds:.3} s of audio before the damage");
        }
        if self.bad_packets > 0 {
            tracing::warn!(file = %self.path.display(), bad_packets = self.bad_packets, "decoded with skipped packets");
        }
        Ok(None)
    }

    fn check_spec(&mut self, spec_rate: u32, ch: usize) -> Result<()> {
        let corrupt = |reason: String| Error::Corrupt {
            path: self.path.clone(),
            reason,
        };
        match self.rate {
            None => {
                if spec_rate == 0 || spec_rate > MAX_SAMPLE_RATE {
                    return Err(corrupt(format!(
                        "sample rate {spec_rate} Hz is outside 1..={MAX_SAMPLE_RATE}"
                    )));
                }
                self.rate = Some(spec_rate);
                self.channels = ch;
                // Saturating float->int cast; the product is a bound, not an allocation size.
                self.max_frames =
                    (self.opts.max_duration_s.max(0.0) * f64::from(spec_rate)).ceil() as u64;
            }
            Some(r) if r != spec_rate => {
                return Err(corrupt(format!(
                    "sample rate changes from {r} Hz to {spec_rate} Hz mid-stream"
                )));
            }
            Some(_) => {}
        }
        if ch != self.channels {
            return Err(corrupt(format!(
                "channel count changes from {} to {ch} mid-stream",
                self.channels
            )));
        }
        Ok(())
    }

    /// Drop the edit list's leading frames and everything past its duration.
    fn apply_edit(&mut self, spec_rate: u32) {
        let Some(e) = self.edit else { return };
        let r = u128::from(spec_rate);
        let ts = u128::from(e.media_timescale);
        let skip = self
            .skip_left
            .get_or_insert_with(|| (u128::from(e.skip) * r / ts) as u64);
        let k = (*skip).min(self.mono.len() as u64) as usize;
        self.mono.drain(..k);
        *skip -= k as u64;
        if let Some(keep) = e.keep {
            let left = self
                .keep_left
                .get_or_insert_with(|| (u128::from(keep) * r / ts) as u64);
            let n = (*left).min(self.mono.len() as u64);
            self.mono.truncate(n as usize);
            *left -= n;
        }
    }
}

/// Channel mean, in f32 and summed in channel order like numpy's `mean(axis=0)` on float32.
/// `out` is cleared first. Files and live capture both mix with this.
pub fn mix_to_mono(interleaved: &[f32], channels: usize, out: &mut Vec<f32>) {
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
