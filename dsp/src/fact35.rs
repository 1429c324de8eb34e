//! The dance field's 35 music features per frame (AI Choreographer / FACT, EDGE's baseline
//! features, LODGE, FineDance, …), computed as those projects compute them with librosa
//! (LODGE `dld/data/utils/audio.py` `extract`, FineDance `data/code/pre_music.py`):
//!
//! ```text
//! sr = fps * 512; y = librosa.load(path, sr)              # channel mean, resampled
//! envelope = onset.onset_strength(y, sr)                   # column 0
//! mfcc = feature.mfcc(y, sr, n_mfcc=20)                    # columns 1..=20
//! chroma = feature.chroma_cens(y, sr, hop 512, n_chroma=12)  # columns 21..=32
//! peaks = onset.onset_detect(onset_envelope=envelope)      # column 33, one-hot
//! beats = beat.beat_track(onset_envelope=envelope, start_bpm, tightness=100)  # column 34
//! ```
//!
//! `start_bpm` comes from an AIST++-style file name when there is one (see
//! [`aist_start_bpm`]), otherwise from `beat.tempo(librosa.load(path)[0])`: the song
//! reloaded at 22050 Hz and its tempo estimated around 120 BPM.
//!
//! [`LibrosaVersion::V07`] is librosa 0.7.2 with resampy 0.3 (what LODGE and FineDance pinned
//! and trained on): resampy `kaiser_best` loading, reflect-padded STFTs, onset mel bands up to
//! 11025 Hz whatever the rate, a 12-bin-per-octave recursive CQT for the chroma.

use std::path::Path;
use std::time::Instant;

use crate::beats_dp::{DpBeatOptions, beat_track_dp, tempo};
use crate::chroma::{chroma_cens, cqt_magnitude_07, cqt_magnitude_010, estimate_tuning};
use crate::decode::{DecodeOptions, decode_file};
use crate::error::{Error, Result};
use crate::kaiser::{KaiserFilter, resample_kaiser};
use crate::mel::{MelFilterbank, MelOptions};
use crate::peaks::{PeakNormalize, onset_detect};
use crate::soxr::resample_soxr_hq;
use crate::spectrum::{PadMode, Stft, Window, power_to_db};

/// Columns of the set.
pub const FACT35_COLUMNS: usize = 35;
/// Hop between frames at every frame rate, samples (sr = fps × 512).
pub const FACT35_HOP: usize = 512;
const N_FFT: usize = 2048;
const N_MELS: usize = 128;
const N_MFCC: usize = 20;
/// The rate LODGE reloads a song at to estimate its tempo (librosa's default `sr`).
const TEMPO_PRIOR_SR: f64 = 22_050.0;
/// `chroma_cens`' `n_octaves` (both versions).
const CHROMA_OCTAVES: usize = 7;
/// The CQT's `sparsity` (librosa's default in both versions).
const CQT_SPARSITY: f64 = 0.01;

/// Which librosa's numbers to reproduce.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LibrosaVersion {
    /// librosa 0.7.2 + resampy 0.3 (LODGE, FineDance and the models trained on them).
    V07,
    /// librosa 0.10.1 + python-soxr (current librosa; 0.10.2 and 0.11 changed the beat
    /// tracker: see [`crate::track_beats`]).
    V010,
}

impl LibrosaVersion {
    /// The librosa release whose numbers these are, e.g. `0.7.2` (for metadata).
    pub fn release(self) -> &'static str {
        match self {
            Self::V07 => "0.7.2",
            Self::V010 => "0.10.1",
        }
    }

    /// Padding of librosa's STFTs in this version.
    fn pad(self) -> PadMode {
        match self {
            Self::V07 => PadMode::Reflect,
            Self::V010 => PadMode::Constant,
        }
    }

    /// Top of the onset envelope's mel bands: 0.7.2 sets `fmax=11025` (even above Nyquist,
    /// leaving the top bands empty at 15360 Hz); 0.10 sets `0.5 * sr`.
    fn onset_fmax(self, sr: f64) -> f64 {
        match self {
            Self::V07 => 11_025.0,
            Self::V010 => 0.5 * sr,
        }
    }

    /// `librosa.load(path, sr)`'s resampling: resampy `kaiser_best` in 0.7.2, soxr HQ in 0.10.
    fn resample(self, y: &[f32], orig_sr: f64, target_sr: f64) -> Result<Vec<f32>> {
        match self {
            Self::V07 => resample_kaiser(y, orig_sr, target_sr, KaiserFilter::Best, false),
            Self::V010 => resample_soxr_hq(y, orig_sr, target_sr, false),
        }
    }

    /// `chroma_cens`' CQT resolution: `bins_per_octave` defaults to `n_chroma` (12) in 0.7.2
    /// and to 36 from 0.10 on; 7 octaves either way.
    fn chroma_bins_per_octave(self) -> usize {
        match self {
            Self::V07 => 12,
            Self::V010 => 36,
        }
    }

    /// `onset_detect`'s normalisation of the envelope.
    fn peak_normalize(self) -> PeakNormalize {
        match self {
            Self::V07 => PeakNormalize::Librosa07,
            Self::V010 => PeakNormalize::Librosa010,
        }
    }

    /// `np.abs(cqt(...))` of this version.
    fn cqt(self, y: &[f32], sr: f64, bpo: usize, tuning: f64) -> Result<(Vec<f64>, usize)> {
        let n_bins = CHROMA_OCTAVES * bpo;
        match self {
            Self::V07 => cqt_magnitude_07(y, sr, FACT35_HOP, n_bins, bpo, tuning, CQT_SPARSITY),
            Self::V010 => cqt_magnitude_010(y, sr, FACT35_HOP, n_bins, bpo, tuning, CQT_SPARSITY),
        }
    }
}

/// Options of [`fact35_from_samples`].
#[derive(Debug, Clone, PartialEq)]
pub struct Fact35Options {
    /// Frames per second: 30 (LODGE, FineDance, EDGE) or 60 (FACT / AIST++).
    pub fps: u32,
    /// Reference librosa.
    pub version: LibrosaVersion,
    /// Tempo prior of the beat tracker; `None` follows the start-BPM rule.
    pub start_bpm: Option<f64>,
}

impl Default for Fact35Options {
    fn default() -> Self {
        Self {
            fps: 30,
            version: LibrosaVersion::V07,
            start_bpm: None,
        }
    }
}

impl Fact35Options {
    /// Analysis rate, `fps × 512` Hz.
    pub fn sample_rate(&self) -> u32 {
        self.fps * FACT35_HOP as u32
    }

    fn validate(&self) -> Result<()> {
        if self.fps != 30 && self.fps != 60 {
            return Err(Error::BadOption {
                name: "fps",
                value: self.fps.to_string(),
                reason: "must be 30 or 60",
            });
        }
        if let Some(b) = self.start_bpm
            && !(b > 0.0 && b.is_finite() && b <= 1000.0)
        {
            return Err(Error::BadOption {
                name: "start_bpm",
                value: b.to_string(),
                reason: "must be in (0, 1000] BPM",
            });
        }
        Ok(())
    }
}

/// Where `start_bpm` came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StartBpmSource {
    /// Given by the caller.
    Given,
    /// The AIST++ music code in the file name.
    FileName,
    /// Estimated from the song at 22050 Hz.
    Estimated,
}

/// Per-stage seconds of one extraction (stages on the second thread overlap the others).
#[non_exhaustive]
#[derive(Debug, Clone, Default)]
pub struct Fact35Stats {
    /// Decoding the file.
    pub decode_s: f64,
    /// Resampling to fps × 512 Hz.
    pub resample_s: f64,
    /// The 2048-point STFT.
    pub stft_s: f64,
    /// Mel bands, MFCC and onset envelope.
    pub mfcc_onset_s: f64,
    /// Tuning, CQT and chroma_cens (second thread).
    pub chroma_s: f64,
    /// The 22050 Hz reload and tempo estimate for the start BPM (second thread; 0 when unused).
    pub start_bpm_s: f64,
    /// Peak picking and beat tracking.
    pub peaks_beats_s: f64,
    /// Wall time.
    pub total_s: f64,
    /// Seconds of audio decoded (of a truncated file, the audio before the damage).
    pub duration_s: f64,
    /// The file ended mid-stream ([`crate::DecodeSummary::truncated`]).
    pub truncated: bool,
    /// Undecodable packets skipped.
    pub bad_packets: usize,
}

/// The features of one song.
#[non_exhaustive]
#[derive(Debug, Clone)]
pub struct Fact35 {
    /// `(frames, 35)` row-major float32.
    pub data: Vec<f32>,
    /// Frames, `1 + ⌊samples / 512⌋` at fps × 512 Hz.
    pub frames: usize,
    /// The beat tracker's tempo prior, BPM.
    pub start_bpm: f64,
    /// Where it came from.
    pub start_bpm_source: StartBpmSource,
    /// The tempo the tracker settled on, BPM.
    pub tempo_bpm: f64,
    /// Estimated tuning, fractions of a semitone.
    pub tuning: f64,
    /// Stage timings.
    pub stats: Fact35Stats,
}

/// LODGE's / EDGE's `_get_tempo`: the fifth `_`-separated field of an AIST++ name
/// (`gBR_sBM_cAll_d04_mBR0_ch01` → `mBR0`) gives the music's BPM — 80 + 10 × digit for
/// the genres BR PO LO MH LH WA KR JS JB, 110 + 5 × digit for HO. `None` for any other name.
pub fn aist_start_bpm(stem: &str) -> Option<f64> {
    let field = stem.split('_').nth(4)?;
    let b = field.as_bytes();
    if b.len() != 4 || !b[3].is_ascii_digit() {
        return None;
    }
    let digit = f64::from(b[3] - b'0');
    match &field[..3] {
        "mBR" | "mPO" | "mLO" | "mMH" | "mLH" | "mWA" | "mKR" | "mJS" | "mJB" => {
            Some(digit * 10.0 + 80.0)
        }
        "mHO" => Some(digit * 5.0 + 110.0),
        _ => None,
    }
}

/// Decode `path` and compute its features; the file stem feeds the start-BPM rule.
pub fn load_fact35(path: &Path, decode: &DecodeOptions, opts: &Fact35Options) -> Result<Fact35> {
    opts.validate()?;
    let t0 = Instant::now();
    let audio = decode_file(path, decode)?;
    let decode_s = t0.elapsed().as_secs_f64();
    let stem = path.file_stem().and_then(|s| s.to_str());
    let mut out = fact35_from_samples(&audio.samples, audio.sample_rate, stem, opts)?;
    out.stats.decode_s = decode_s;
    out.stats.duration_s = audio.duration_s;
    out.stats.truncated = audio.truncated;
    out.stats.bad_packets = audio.bad_packets;
    out.stats.total_s = t0.elapsed().as_secs_f64();
    Ok(out)
}

/// Shortest input accepted, seconds: the lowest CQT octave (1/64 of the rate) must still
/// exceed its 64-sample half window.
pub const FACT35_MIN_SECONDS: f64 = 0.5;

/// The features of mono `samples` at `sample_rate` (librosa's `load` output before
/// resampling). `stem` is the file name without extension, for the start-BPM rule.
pub fn fact35_from_samples(
    samples: &[f32],
    sample_rate: u32,
    stem: Option<&str>,
    opts: &Fact35Options,
) -> Result<Fact35> {
    opts.validate()?;
    let t0 = Instant::now();
    if (samples.len() as f64) < FACT35_MIN_SECONDS * f64::from(sample_rate) {
        return Err(Error::TooShort {
            seconds: samples.len() as f64 / f64::from(sample_rate.max(1)),
            min_s: FACT35_MIN_SECONDS,
            what: "the fact35 music features",
        });
    }
    let sr = f64::from(opts.sample_rate());
    let native = f64::from(sample_rate);
    let version = opts.version;
    let (start_bpm, start_bpm_source) = match (opts.start_bpm, stem.and_then(aist_start_bpm)) {
        (Some(b), _) => (Some(b), StartBpmSource::Given),
        (None, Some(b)) => (Some(b), StartBpmSource::FileName),
        (None, None) => (None, StartBpmSource::Estimated),
    };
    let mut stats = Fact35Stats::default();
    std::thread::scope(|scope| -> Result<Fact35> {
        // The tempo prior's reload runs beside the main resampling.
        let prior = scope.spawn(move || -> Result<(f64, f64)> {
            let t = Instant::now();
            let bpm = match start_bpm {
                Some(b) => b,
                None => {
                    let y22 = version.resample(samples, native, TEMPO_PRIOR_SR)?;
                    let env = onset_envelope(&y22, TEMPO_PRIOR_SR, version)?;
                    tempo(&env, TEMPO_PRIOR_SR, FACT35_HOP, 120.0)
                }
            };
            Ok((bpm, t.elapsed().as_secs_f64()))
        });
        let t = Instant::now();
        let y = version.resample(samples, native, sr)?;
        stats.resample_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let stft = Stft::new(N_FFT, FACT35_HOP, Window::Hann, version.pad())?;
        let mags = stft.magnitudes(&y)?;
        let frames = stft.frame_count(y.len());
        let power: Vec<f32> = mags.iter().map(|m| m * m).collect();
        stats.stft_s = t.elapsed().as_secs_f64();
        // y and the magnitudes move to the chroma thread; the power stays here.
        let chroma = scope.spawn(move || -> Result<(Vec<f64>, f64, f64)> {
            let t = Instant::now();
            let bpo = version.chroma_bins_per_octave();
            let tuning = estimate_tuning(&mags, N_FFT, sr, bpo);
            let (cqt, cqt_frames) = version.cqt(&y, sr, bpo, tuning)?;
            let mut cens = chroma_cens(&cqt, CHROMA_OCTAVES * bpo, bpo, cqt_frames);
            fit_frames(&mut cens, cqt_frames, frames);
            Ok((cens, tuning, t.elapsed().as_secs_f64()))
        });
        let t = Instant::now();
        let mfcc = mfcc_from_power(&power, frames, sr);
        let env = onset_from_power(&power, frames, sr, version.onset_fmax(sr));
        stats.mfcc_onset_s = t.elapsed().as_secs_f64();
        let (bpm, prior_s) = prior
            .join()
            .map_err(|_| Error::WorkerPanicked { stage: "start-BPM" })??;
        stats.start_bpm_s = if start_bpm.is_some() { 0.0 } else { prior_s };
        let t = Instant::now();
        let peaks = onset_detect(&env, sr, FACT35_HOP, version.peak_normalize());
        let beat_opts = DpBeatOptions {
            start_bpm: bpm,
            ..DpBeatOptions::default()
        };
        let (tempo_bpm, beats) = beat_track_dp(&env, sr, FACT35_HOP, &beat_opts);
        stats.peaks_beats_s = t.elapsed().as_secs_f64();
        let (cens, tuning, chroma_s) = chroma
            .join()
            .map_err(|_| Error::WorkerPanicked { stage: "chroma" })??;
        stats.chroma_s = chroma_s;
        let mut data = vec![0.0f32; frames * FACT35_COLUMNS];
        for (t, row) in data.chunks_exact_mut(FACT35_COLUMNS).enumerate() {
            row[0] = env[t];
            for k in 0..N_MFCC {
                row[1 + k] = mfcc[k * frames + t];
            }
            for c in 0..12 {
                row[21 + c] = cens[c * frames + t] as f32;
            }
        }
        for p in peaks {
            data[p * FACT35_COLUMNS + 33] = 1.0;
        }
        for b in beats {
            data[b * FACT35_COLUMNS + 34] = 1.0;
        }
        stats.total_s = t0.elapsed().as_secs_f64();
        Ok(Fact35 {
            data,
            frames,
            start_bpm: bpm,
            start_bpm_source,
            tempo_bpm,
            tuning,
            stats,
        })
    })
}

/// A `(rows, have)` array cut or zero-extended to `(rows, want)` frames. The CQT's frame count
/// equals the STFT's for every length the recipe accepts; this only guards the assembly.
fn fit_frames(x: &mut Vec<f64>, have: usize, want: usize) {
    if have == want {
        return;
    }
    let rows = x.len() / have.max(1);
    let mut out = vec![0.0; rows * want];
    for r in 0..rows {
        let n = have.min(want);
        out[r * want..r * want + n].copy_from_slice(&x[r * have..r * have + n]);
    }
    *x = out;
}

/// `(frames, 128)` mel power from `(frames, 1025)` STFT power, float32 as librosa's dot.
fn mel_power(power: &[f32], frames: usize, sr: f64, fmax: f64) -> Vec<f32> {
    let o = MelOptions {
        sample_rate: sr as u32,
        n_fft: N_FFT,
        n_mels: N_MELS,
        fmax,
        ..MelOptions::default()
    };
    let fb = MelFilterbank::new(&o);
    let nb = N_FFT / 2 + 1;
    let mut mel = vec![0.0f32; frames * N_MELS];
    for (spec, out) in power.chunks_exact(nb).zip(mel.chunks_exact_mut(N_MELS)) {
        fb.apply(spec, out);
    }
    mel
}

/// `feature.mfcc(y, sr, n_mfcc=20)`: DCT-II (orthonormal) of `power_to_db(melspectrogram)`
/// (128 bands to sr/2, top_db 80), first 20 coefficients, `(20, frames)` row-major.
pub fn mfcc_from_power(power: &[f32], frames: usize, sr: f64) -> Vec<f32> {
    let mut db = mel_power(power, frames, sr, sr / 2.0);
    power_to_db(&mut db, Some(80.0));
    let n = N_MELS as f64;
    // scipy.fftpack.dct(type=2, norm="ortho"): sqrt(1/N) for k = 0, sqrt(2/N) otherwise.
    let basis: Vec<f64> = (0..N_MFCC)
        .flat_map(|k| {
            let scale = if k == 0 {
                (1.0 / n).sqrt()
            } else {
                (2.0 / n).sqrt()
            };
            (0..N_MELS).map(move |m| {
                scale * (std::f64::consts::PI * k as f64 * (2 * m + 1) as f64 / (2.0 * n)).cos()
            })
        })
        .collect();
    let mut out = vec![0.0f32; N_MFCC * frames];
    for (t, frame) in db.chunks_exact(N_MELS).enumerate() {
        for k in 0..N_MFCC {
            let row = &basis[k * N_MELS..(k + 1) * N_MELS];
            let v: f64 = row.iter().zip(frame).map(|(b, &x)| b * f64::from(x)).sum();
            out[k * frames + t] = v as f32;
        }
    }
    out
}

/// `onset.onset_strength(y, sr)` from STFT power: dB mel bands up to `fmax` (top_db 80), the
/// positive frame-to-frame differences averaged over bands (float32, bands summed in order),
/// shifted right by 3 frames (lag 1 + n_fft / (2 hop)) and cut to the frame count.
pub fn onset_from_power(power: &[f32], frames: usize, sr: f64, fmax: f64) -> Vec<f32> {
    let mut db = mel_power(power, frames, sr, fmax);
    power_to_db(&mut db, Some(80.0));
    let shift = 1 + N_FFT / (2 * FACT35_HOP);
    let mut env = vec![0.0f32; frames];
    for (j, e) in env.iter_mut().skip(shift).enumerate() {
        if j + 1 >= frames {
            break;
        }
        let (a, b) = (
            &db[j * N_MELS..(j + 1) * N_MELS],
            &db[(j + 1) * N_MELS..(j + 2) * N_MELS],
        );
        let sum = a
            .iter()
            .zip(b)
            .fold(0.0f32, |s, (x, y)| s + (y - x).max(0.0));
        *e = sum / N_MELS as f32;
    }
    env
}

/// The onset envelope of a signal already at `sr` (STFT, mel bands to the version's fmax).
pub fn onset_envelope(y: &[f32], sr: f64, version: LibrosaVersion) -> Result<Vec<f32>> {
    let stft = Stft::new(N_FFT, FACT35_HOP, Window::Hann, version.pad())?;
    let power: Vec<f32> = stft.magnitudes(y)?.iter().map(|m| m * m).collect();
    let frames = stft.frame_count(y.len());
    Ok(onset_from_power(&power, frames, sr, version.onset_fmax(sr)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn aist_names_give_their_bpm_and_others_none() {
        assert_eq!(aist_start_bpm("gBR_sBM_cAll_d04_mBR0_ch01"), Some(80.0));
        assert_eq!(aist_start_bpm("gHO_sFM_cAll_d19_mHO5_ch09"), Some(135.0));
        assert_eq!(aist_start_bpm("x_x_x_x_mJB9"), Some(170.0));
        // LODGE's rule needs the fifth field: AIST++'s own music files (mBR0.wav) do not match.
        assert_eq!(aist_start_bpm("mBR0"), None);
        assert_eq!(aist_start_bpm("a_b_c_d_mXX0_e"), None);
        assert_eq!(aist_start_bpm("a_b_c_d_mBRx"), None);
        assert_eq!(aist_start_bpm("a_b_c_d_mBR10"), None);
        assert_eq!(aist_start_bpm("001"), None);
    }

    #[test]
    fn bad_options_and_short_input_fail_cleanly() {
        let o = Fact35Options {
            fps: 25,
            ..Default::default()
        };
        assert!(fact35_from_samples(&[0.0; 44_100], 44_100, None, &o).is_err());
        let o = Fact35Options {
            start_bpm: Some(f64::NAN),
            ..Default::default()
        };
        assert!(fact35_from_samples(&[0.0; 44_100], 44_100, None, &o).is_err());
        let o = Fact35Options::default();
        assert!(fact35_from_samples(&[0.0; 100], 44_100, None, &o).is_err());
    }

    #[test]
    fn silence_gives_finite_features_without_peaks_or_beats() {
        let f =
            fact35_from_samples(&[0.0; 22_050], 22_050, None, &Fact35Options::default()).unwrap();
        assert_eq!(f.frames, 1 + 15_360 / 512);
        assert!(f.data.iter().all(|x| x.is_finite()));
        assert!(f.data.chunks(35).all(|r| r[33] == 0.0 && r[34] == 0.0));
    }
}
