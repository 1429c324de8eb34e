//! Exactness of the `fact35` music features against librosa 0.7.2 + resampy 0.3.1 and against
//! librosa 0.10.1 + python-soxr 1.1.0, piece by piece and end to end, on the golden fixtures of `tests/golden/make_fact35.py` (a 4 s
//! excerpt of "Vibe Ace" with a clear beat, 4 s of Brahms' Hungarian Dance No. 5 played
//! rubato, a synthetic 120 BPM click track with an AIST++-style name; at 30 and 60 fps; plus
//! the onset envelopes of both whole songs for the peak picker and beat tracker alone).
//!
//! Tolerances. Continuous columns: max |error| ≤ 1e-3 of the column's range over the fixture,
//! the bound; the only allowed differences are float32-vs-float64 arithmetic (librosa
//! mixes float32 arrays with float64 FFTs; this crate does the same, with different summation
//! orders). One-hot columns, tuning, tempo and beats: identical.

// Helpers outside #[test] fns are test code too: a panic there is a failed test.
#![allow(clippy::unwrap_used)]

mod golden;

use choreo_dsp::{
    DecodeOptions, DpBeatOptions, Fact35Options, KaiserFilter, LibrosaVersion, PadMode,
    PeakNormalize, Stft, Window, beat_track_dp, chroma_cens, cqt_magnitude_07, cqt_magnitude_010,
    decode_file, estimate_tuning, fact35_from_samples, mfcc_from_power, onset_detect,
    onset_from_power, resample_kaiser, resample_soxr_hq, tempo_dp,
};

const CLIPS: [&str; 3] = [
    "beat_vibe_ace",
    "rubato_hungarian",
    "click_sFM_cAll_d00_mBR4_ch00",
];
const LONG: [&str; 2] = ["long_vibe_ace", "long_hungarian"];
/// The bound for continuous columns, as a fraction of each column's range.
const REL_TOL: f64 = 1e-3;

fn decode(clip: &str) -> (Vec<f32>, u32) {
    let a = decode_file(
        &golden::dir().join(format!("{clip}.flac")),
        &DecodeOptions::default(),
    )
    .unwrap();
    (a.samples, a.sample_rate)
}

/// What differs between the two reference librosas, as their source says (see `fact35.rs`).
#[derive(Clone, Copy)]
struct Reference {
    version: LibrosaVersion,
    /// Fixture name suffix.
    tag: &'static str,
    pad: PadMode,
    /// The onset envelope's top mel frequency at the rate.
    onset_fmax: fn(f64) -> f64,
    chroma_bpo: usize,
    peaks: PeakNormalize,
}

const REFERENCES: [Reference; 2] = [
    Reference {
        version: LibrosaVersion::V07,
        tag: "lr07",
        pad: PadMode::Reflect,
        onset_fmax: |_| 11_025.0,
        chroma_bpo: 12,
        peaks: PeakNormalize::Librosa07,
    },
    Reference {
        version: LibrosaVersion::V010,
        tag: "lr010",
        pad: PadMode::Constant,
        onset_fmax: |sr| 0.5 * sr,
        chroma_bpo: 36,
        peaks: PeakNormalize::Librosa010,
    },
];

fn mags(y: &[f32], pad: PadMode) -> (Vec<f32>, usize) {
    let stft = Stft::new(2048, 512, Window::Hann, pad).unwrap();
    (stft.magnitudes(y).unwrap(), stft.frame_count(y.len()))
}

fn every_clip_reference_and_rate() -> Vec<(&'static str, Reference, u32)> {
    let mut out = Vec::new();
    for clip in CLIPS {
        for r in REFERENCES {
            for fps in [30, 60] {
                out.push((clip, r, fps));
            }
        }
    }
    out
}

fn max_abs(a: &[f32], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - y).abs())
        .fold(0.0, f64::max)
}

/// resampy's loop, float32 accumulation included, is reproduced operation for operation and
/// the tables are regenerated bit for bit, so the only differences left are the last bits of
/// `sin`/`exp` inside the table (≤ 1e-16) amplified by ~300 float32 roundings: 1e-6 is a few
/// float32 ulps at full scale.
#[test]
fn kaiser_resampler_matches_resampy_03_both_filters_up_and_down() {
    let g = golden::load("resampy_lr07");
    let x = g["x"].f32();
    let sr = g["sr"].scalar();
    for (key, to, filter, from) in [
        ("best_15360", 15_360.0, KaiserFilter::Best, sr),
        ("best_48000", 48_000.0, KaiserFilter::Best, sr),
        ("fast_half", 1.0, KaiserFilter::Fast, 2.0),
    ] {
        let want = &g[key].data;
        let got = resample_kaiser(&x, from, to, filter, false).unwrap();
        // resampy yields int(len * ratio) samples; librosa pads to ceil (checked below).
        let err = max_abs(&got[..want.len()], want);
        eprintln!("{key}: max |d| = {err:.2e}");
        assert!(err <= 1e-6, "{key}: {err}");
    }
}

/// librosa.load(path, sr=fps*512) = decode + channel mean + the version's resampler +
/// fix_length; same bound as above (the FLAC decodes to identical samples in libsndfile and
/// symphonia; soxr is the same library in python-soxr and here, so 0.10 is exact).
#[test]
fn load_matches_both_librosas_at_30_and_60_fps() {
    for (clip, r, fps) in every_clip_reference_and_rate() {
        let (x, native) = decode(clip);
        {
            let g = golden::load(&format!("{clip}_{fps}_{}", r.tag));
            let sr = f64::from(fps * 512);
            let y = match r.version {
                LibrosaVersion::V07 => {
                    resample_kaiser(&x, f64::from(native), sr, KaiserFilter::Best, false)
                }
                _ => resample_soxr_hq(&x, f64::from(native), sr, false),
            }
            .unwrap();
            let (head, tail) = if let Some(full) = g.get("y") {
                assert_eq!(y.len(), full.data.len(), "{clip} {fps}");
                (full.data.clone(), Vec::new())
            } else {
                (g["y_head"].data.clone(), g["y_tail"].data.clone())
            };
            let mut err = max_abs(&y[..head.len()], &head);
            if !tail.is_empty() {
                err = err.max(max_abs(&y[y.len() - tail.len()..], &tail));
            }
            eprintln!("{clip} {fps} fps {}: load max |d| = {err:.2e}", r.tag);
            assert!(err <= 1e-6, "{clip} {fps}: {err}");
        }
    }
}

/// MFCC and the onset envelope from librosa's own 15360 Hz signal: reflect-padded (0.7.2) or
/// zero-padded (0.10) STFT, 128 mel bands (to sr/2 for MFCC, to 11025 Hz (0.7.2) or sr/2 (0.10)
/// for the envelope), power_to_db, DCT-II ortho /
/// positive flux. float32 STFT magnitudes and mel sums carry ~1e-7 relative error; in dB near
/// the −80 dB floor that is ~1e-5 dB, far inside 1e-3 of the ranges (hundreds of units for
/// MFCC 0, tens for the rest, ~1–5 for the envelope).
#[test]
fn mfcc_and_onset_envelope_match_both_librosas() {
    for (clip, r) in CLIPS.iter().flat_map(|c| REFERENCES.map(|r| (c, r))) {
        let g = golden::load(&format!("{clip}_30_{}", r.tag));
        let y = g["y"].f32();
        let (mags, frames) = mags(&y, r.pad);
        let power: Vec<f32> = mags.iter().map(|m| m * m).collect();
        let mfcc = mfcc_from_power(&power, frames, 15_360.0);
        let want = &g["mfcc"];
        assert_eq!(want.shape, vec![20, frames], "{clip}");
        let got: Vec<f64> = mfcc.iter().map(|&x| f64::from(x)).collect();
        let (row, err) = golden::worst_row_error(&got, &want.data, 20);
        eprintln!("{clip}: MFCC worst row {row}: {err:.2e} of range");
        assert!(err <= REL_TOL, "{clip}: MFCC {row}: {err}");
        let env = onset_from_power(&power, frames, 15_360.0, (r.onset_fmax)(15_360.0));
        let got: Vec<f64> = env.iter().map(|&x| f64::from(x)).collect();
        let (_, err) = golden::worst_row_error(&got, &g["onset_env"].data, 1);
        eprintln!("{clip}: onset envelope {err:.2e} of range");
        assert!(err <= REL_TOL, "{clip}: onset {err}");
    }
}

/// estimate_tuning (piptrack + a 0.01-bin histogram) is a discrete decision: identical.
#[test]
fn tuning_matches_both_librosas() {
    for (clip, r) in CLIPS.iter().flat_map(|c| REFERENCES.map(|r| (c, r))) {
        let g = golden::load(&format!("{clip}_30_{}", r.tag));
        let (mags, _) = mags(&g["y"].f32(), r.pad);
        let got = estimate_tuning(&mags, 2048, 15_360.0, r.chroma_bpo);
        let want = g["tuning"].scalar();
        eprintln!("{clip} {}: tuning {got} (librosa {want})", r.tag);
        assert!((got - want).abs() < 1e-9, "{clip}: {got} vs {want}");
    }
}

/// The CQT from librosa's signal and tuning: 0.7.2's recursive one (12 bins per octave, resampy
/// halvings) and 0.10's per-octave wavelet filters (36 bins per octave, soxr halvings). Their
/// float32 octave signals and complex64 frames and products give ~1e-7 relative error per bin;
/// the bound is 1e-3 of each bin's range.
#[test]
fn cqt_matches_both_librosas() {
    for (clip, r) in CLIPS.iter().flat_map(|c| REFERENCES.map(|r| (c, r))) {
        let g = golden::load(&format!("{clip}_30_{}", r.tag));
        let y = g["y"].f32();
        let bpo = r.chroma_bpo;
        let cqt = match r.version {
            LibrosaVersion::V07 => cqt_magnitude_07,
            _ => cqt_magnitude_010,
        };
        let (cqt, frames) =
            cqt(&y, 15_360.0, 512, 7 * bpo, bpo, g["tuning"].scalar(), 0.01).unwrap();
        let want = &g["cqt_mag"];
        assert_eq!(want.shape, vec![7 * bpo, frames], "{clip}");
        let (row, err) = golden::worst_row_error(&cqt, &want.data, 7 * bpo);
        eprintln!("{clip} {}: CQT worst bin {row}: {err:.2e} of range", r.tag);
        assert!(err <= REL_TOL, "{clip}: CQT bin {row}: {err}");
    }
}

/// chroma_cens from librosa's own CQT magnitudes: the same float64 operations in the same
/// order, so the quantisation steps fall identically and the bound is met with room.
#[test]
fn chroma_cens_matches_both_librosas() {
    for (clip, r) in CLIPS.iter().flat_map(|c| REFERENCES.map(|r| (c, r))) {
        let g = golden::load(&format!("{clip}_30_{}", r.tag));
        let c = &g["cqt_mag"];
        let cens = chroma_cens(&c.data, c.shape[0], r.chroma_bpo, c.shape[1]);
        let (row, err) = golden::worst_row_error(&cens, &g["chroma_cens"].data, 12);
        eprintln!(
            "{clip} {}: CENS worst chroma {row}: {err:.2e} of range",
            r.tag
        );
        assert!(err <= REL_TOL, "{clip}: chroma {row}: {err}");
    }
}

/// onset_detect on librosa's envelope: identical peak frames, at both rates and on the whole
/// songs (at 15360 Hz pre_max rounds to 0 frames, so adjacent peaks occur and are kept).
#[test]
fn onset_peaks_match_both_librosas() {
    let mut cases: Vec<(String, f64, PeakNormalize)> = Vec::new();
    for r in REFERENCES {
        for clip in CLIPS {
            cases.push((format!("{clip}_30_{}", r.tag), 15_360.0, r.peaks));
            cases.push((format!("{clip}_60_{}", r.tag), 30_720.0, r.peaks));
        }
        for long in LONG {
            cases.push((format!("{long}_30_{}", r.tag), 15_360.0, r.peaks));
        }
    }
    for (name, sr, norm) in cases {
        let g = golden::load(&name);
        let got = onset_detect(&g["onset_env"].f32(), sr, 512, norm);
        assert_eq!(got, g["peaks"].usize(), "{name}");
    }
}

/// beat_track(onset_envelope, start_bpm, tightness=100) on librosa's envelope: identical tempo
/// and beat frames, including the 0.7.2 trim that drops the last strong beat.
#[test]
fn beats_match_both_librosas() {
    for (clip, r, fps) in every_clip_reference_and_rate() {
        {
            let name = format!("{clip}_{fps}_{}", r.tag);
            let g = golden::load(&name);
            let opts = DpBeatOptions {
                start_bpm: g["start_bpm"].scalar(),
                ..DpBeatOptions::default()
            };
            let (tempo, beats) =
                beat_track_dp(&g["onset_env"].f32(), f64::from(fps * 512), 512, &opts);
            assert_eq!(tempo, g["tempo"].scalar(), "{name}");
            assert_eq!(beats, g["beats"].usize(), "{name}");
        }
    }
    for (long, r) in LONG.iter().flat_map(|c| REFERENCES.map(|r| (c, r))) {
        let name = format!("{long}_30_{}", r.tag);
        let g = golden::load(&name);
        for bpm in [120.0, 95.0] {
            let opts = DpBeatOptions {
                start_bpm: bpm,
                ..DpBeatOptions::default()
            };
            let (tempo, beats) = beat_track_dp(&g["onset_env"].f32(), 15_360.0, 512, &opts);
            assert_eq!(tempo, g[&format!("tempo_{bpm}")].scalar(), "{name} {bpm}");
            assert_eq!(beats, g[&format!("beats_{bpm}")].usize(), "{name} {bpm}");
        }
    }
}

/// The start-BPM fallback: beat.tempo(librosa.load(path)[0]) — the song at 22050 Hz, its
/// envelope, the tempogram around 120 BPM — from librosa's envelope: identical.
#[test]
fn start_bpm_estimate_matches_both_librosas() {
    for (clip, r) in ["beat_vibe_ace", "rubato_hungarian"]
        .iter()
        .flat_map(|c| REFERENCES.map(|r| (c, r)))
    {
        let g = golden::load(&format!("{clip}_30_{}", r.tag));
        let got = tempo_dp(&g["env22"].f32(), 22_050.0, 512, 120.0);
        assert_eq!(got, g["start_bpm"].scalar(), "{clip}");
    }
}

/// The whole recipe from the FLAC file: every continuous column within 1e-3 of its range,
/// the peak and beat columns identical.
#[test]
fn all_35_columns_match_both_librosas_end_to_end() {
    for (clip, r, fps) in every_clip_reference_and_rate() {
        let (x, native) = decode(clip);
        {
            let name = format!("{clip}_{fps}_{}", r.tag);
            let g = golden::load(&name);
            let o = Fact35Options {
                fps,
                version: r.version,
                ..Default::default()
            };
            let f = fact35_from_samples(&x, native, Some(clip), &o).unwrap();
            let want = &g["features"];
            assert_eq!(want.shape, vec![f.frames, 35], "{name}");
            assert_eq!(f.start_bpm, g["start_bpm"].scalar(), "{name}");
            for col in 0..35 {
                let w: Vec<f64> = want.data.iter().skip(col).step_by(35).copied().collect();
                let got: Vec<f64> = f
                    .data
                    .iter()
                    .skip(col)
                    .step_by(35)
                    .map(|&x| f64::from(x))
                    .collect();
                if col >= 33 {
                    assert_eq!(got, w, "{name}: one-hot column {col}");
                } else {
                    let (_, err) = golden::worst_row_error(&got, &w, 1);
                    assert!(err <= REL_TOL, "{name}: column {col}: {err:.2e} of range");
                }
            }
        }
    }
}
