//! Decoding every listed format (files made at test time with ffmpeg/sox in a temp dir) and the
//! bad-input list of the audio issue: each gives a clear error or a documented result.

// Helpers outside #[test] fns are test code too: a panic there is a failed test.
#![allow(clippy::unwrap_used)]

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use choreo_dsp::{DecodeOptions, Error, MelOptions, decode_file, load_log_mel, log_mel};

/// Run a tool, panicking with its stderr if it fails (the tools are installed by scripts/setup).
fn tool(cmd: &str, args: &[&str]) {
    let out = Command::new(cmd)
        .args(args)
        .output()
        .unwrap_or_else(|e| panic!("{cmd}: {e}"));
    assert!(
        out.status.success(),
        "{cmd} {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn ffmpeg(args: &[&str]) {
    let mut a = vec!["-hide_banner", "-loglevel", "error", "-y"];
    a.extend_from_slice(args);
    tool("ffmpeg", &a);
}

/// A 3 s, 44.1 kHz stereo test signal (two tones + noise) as 16-bit WAV.
fn source_wav(dir: &Path) -> PathBuf {
    let p = dir.join("src.wav");
    tool(
        "sox",
        &[
            "-n",
            "-r",
            "44100",
            "-c",
            "2",
            "-b",
            "16",
            p.to_str().unwrap(),
            "synth",
            "3",
            "sine",
            "440",
            "sine",
            "1250",
            "gain",
            "-6",
        ],
    );
    p
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn every_listed_format_decodes_with_the_wav_length() {
    let dir = tempfile::tempdir().unwrap();
    let src = source_wav(dir.path());
    let reference = decode_file(&src, &DecodeOptions::default()).unwrap();
    assert_eq!(reference.sample_rate, 44_100);
    assert_eq!(reference.source_channels, 2);
    assert_eq!(reference.samples.len(), 3 * 44_100);
    let d = dir.path();
    // (file, ffmpeg codec args, max length difference in samples, lossless?)
    let cases: Vec<(&str, Vec<&str>, usize, bool)> = vec![
        ("s24.wav", vec!["-c:a", "pcm_s24le"], 0, true),
        ("s32.wav", vec!["-c:a", "pcm_s32le"], 0, true),
        ("f32.wav", vec!["-c:a", "pcm_f32le"], 0, true),
        ("x.flac", vec!["-c:a", "flac"], 0, true),
        ("x.aiff", vec!["-c:a", "pcm_s16be"], 0, true),
        ("alac.m4a", vec!["-c:a", "alac"], 0, true),
        // LAME writes a gapless (Xing/LAME) header: exact length expected.
        (
            "x.mp3",
            vec!["-c:a", "libmp3lame", "-b:a", "192k"],
            2,
            false,
        ),
        ("x.ogg", vec!["-c:a", "libvorbis", "-q:a", "5"], 2, false),
        // AAC: priming 1024 frames signalled by the MP4 edit list.
        ("aac.m4a", vec!["-c:a", "aac", "-b:a", "192k"], 2, false),
    ];
    for (name, codec, tol, lossless) in cases {
        let out = d.join(name);
        let mut args = vec!["-i", s(&src)];
        args.extend(codec);
        args.push(s(&out));
        ffmpeg(&args);
        let got =
            decode_file(&out, &DecodeOptions::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(got.sample_rate, 44_100, "{name}");
        assert_eq!(got.source_channels, 2, "{name}");
        let diff = got.samples.len().abs_diff(reference.samples.len());
        eprintln!("{name}: {} samples ({diff} off)", got.samples.len());
        assert!(
            diff <= tol,
            "{name}: {} vs {} samples",
            got.samples.len(),
            reference.samples.len()
        );
        if lossless {
            // Same 16-bit source: bit-identical after scaling (24/32-bit and float carry it exactly).
            assert_eq!(got.samples, reference.samples, "{name}");
        } else {
            // Lossy: aligned (no leftover encoder delay) — the error over the middle second is far
            // below the signal (RMS ~0.35); a 1-sample shift of the 1250 Hz tone would give ~0.05.
            let n = reference.samples.len().min(got.samples.len());
            let mid = 44_100..(2 * 44_100).min(n);
            let err = mid
                .clone()
                .map(|i| f64::from(got.samples[i] - reference.samples[i]).powi(2))
                .sum::<f64>()
                / mid.len() as f64;
            assert!(err.sqrt() < 0.02, "{name}: rms error {}", err.sqrt());
        }
    }
}

#[test]
fn opus_gets_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let src = source_wav(dir.path());
    let out = dir.path().join("x.opus");
    ffmpeg(&["-i", s(&src), "-c:a", "libopus", s(&out)]);
    let e = decode_file(&out, &DecodeOptions::default()).unwrap_err();
    assert!(matches!(e, Error::OpusUnsupported { .. }), "{e}");
    let msg = e.to_string();
    let fix = format!(
        "ffmpeg -i {} {}",
        out.display(),
        out.with_extension("flac").display()
    );
    assert!(msg.contains(&fix), "{msg}");
}

fn expect_err(path: &Path) -> String {
    let e = decode_file(path, &DecodeOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(path.file_name().unwrap().to_str().unwrap()),
        "error must name the file: {e}"
    );
    assert!(!e.contains('\n'), "one line: {e}");
    e
}

#[test]
fn bad_inputs_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let src = source_wav(d);

    // Empty file.
    let empty = d.join("empty.wav");
    std::fs::write(&empty, b"").unwrap();
    assert!(expect_err(&empty).contains("empty"));

    // Random bytes with audio extensions (fixed LCG: reproducible).
    let mut state = 42u64;
    let noise: Vec<u8> = (0..100_000)
        .map(|_| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 56) as u8
        })
        .collect();
    for name in [
        "random.mp3",
        "random.wav",
        "random.flac",
        "random.ogg",
        "random.m4a",
    ] {
        let p = d.join(name);
        std::fs::write(&p, &noise).unwrap();
        match decode_file(&p, &DecodeOptions::default()) {
            Err(e) => {
                let m = e.to_string();
                assert!(m.contains(name) && !m.contains('\n'), "{m}");
            }
            // The MP3 demuxer resynchronises on anything that looks like a frame header; random
            // data may decode to a few bogus frames. Documented: accepted as (garbage) audio.
            Ok(a) => assert!(a.samples.iter().all(|v| v.is_finite()), "{name}"),
        }
    }

    // Zero-length audio: a valid WAV with no samples.
    let zero = d.join("zero.wav");
    tool(
        "sox",
        &[
            "-n",
            "-r",
            "16000",
            "-c",
            "1",
            "-b",
            "16",
            s(&zero),
            "trim",
            "0",
            "0",
        ],
    );
    assert!(expect_err(&zero).contains("no audio samples"));

    // Too long for the configured maximum.
    let mut short_limit = DecodeOptions::default();
    short_limit.max_duration_s = 1.0;
    let e = decode_file(&src, &short_limit).unwrap_err().to_string();
    assert!(e.contains("longer than the limit of 1 s"), "{e}");

    // File larger than max_file_bytes: refused before opening.
    let mut tiny = DecodeOptions::default();
    tiny.max_file_bytes = 1000;
    let e = decode_file(&src, &tiny).unwrap_err().to_string();
    assert!(e.contains("more than the limit of 1000 bytes"), "{e}");

    // A missing file.
    assert!(expect_err(&d.join("missing.wav")).contains("No such file"));
}

#[test]
fn truncated_files_decode_up_to_the_damage_or_fail_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let src = source_wav(d);
    for (name, codec) in [
        ("t.wav", "pcm_s16le"),
        ("t.flac", "flac"),
        ("t.mp3", "libmp3lame"),
        ("t.ogg", "libvorbis"),
        ("t.m4a", "aac"),
    ] {
        let full = d.join(format!("full_{name}"));
        ffmpeg(&["-i", s(&src), "-c:a", codec, s(&full)]);
        let bytes = std::fs::read(&full).unwrap();
        // Cut mid-frame at an odd byte, in the middle of the file.
        let cut = d.join(name);
        std::fs::write(&cut, &bytes[..bytes.len() / 2 + 1]).unwrap();
        match decode_file(&cut, &DecodeOptions::default()) {
            Ok(a) => {
                eprintln!("{name}: truncated -> {} samples", a.samples.len());
                assert!(
                    a.samples.len() < 3 * 44_100 && !a.samples.is_empty(),
                    "{name}"
                );
            }
            Err(e) => {
                let m = e.to_string();
                eprintln!("{name}: truncated -> {m}");
                assert!(m.contains(name) && !m.contains('\n'), "{m}");
            }
        }
        // A cut OGG that decodes says so (issue 23 item 8: recorded in the provenance, failed on
        // request); the whole file does not. This 3 s file (15 kB) cut at half fails to open
        // (the error above; cuts at 30 % and 50 % measured so), cut at 90 % it opens and decodes
        // up to the cut.
        if name == "t.ogg" {
            let truncated = |p: &Path| {
                load_log_mel(p, &DecodeOptions::default(), &MelOptions::default())
                    .map(|(_, stats)| stats.truncated)
            };
            assert!(!truncated(&full).unwrap());
            let late_cut = d.join("late_cut.ogg");
            std::fs::write(&late_cut, &bytes[..bytes.len() * 9 / 10 + 1]).unwrap();
            assert!(truncated(&late_cut).unwrap(), "a cut OGG reported whole");
        }
    }
}

#[test]
fn wrong_extension_is_detected_by_content() {
    let dir = tempfile::tempdir().unwrap();
    let src = source_wav(dir.path());
    let disguised = dir.path().join("really_a_wav.mp3");
    std::fs::copy(&src, &disguised).unwrap();
    // Documented: the container is probed by content; the extension is only a hint.
    let a = decode_file(&disguised, &DecodeOptions::default()).unwrap();
    assert_eq!(a.samples.len(), 3 * 44_100);
}

#[test]
fn digital_silence_gives_the_floor() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("silence.wav");
    // -D: no dither, or sox adds noise when writing 16 bits.
    tool(
        "sox",
        &[
            "-D",
            "-n",
            "-r",
            "16000",
            "-c",
            "1",
            "-b",
            "16",
            s(&p),
            "trim",
            "0",
            "2",
        ],
    );
    let (mel, stats) = load_log_mel(&p, &DecodeOptions::default(), &MelOptions::default()).unwrap();
    assert_eq!(stats.frames, 1 + 32_000 / 512);
    // Documented result: every value is 10 log10(amin) = -100 dB (no NaN/-inf).
    assert!(
        mel.iter().all(|&v| v == -100.0),
        "{:?}",
        mel.iter().take(3).collect::<Vec<_>>()
    );
}

/// Write a mono float32 WAV by hand (sox/ffmpeg refuse to make NaN).
fn float_wav(path: &Path, samples: &[f32]) {
    let data_len = (samples.len() * 4) as u32;
    let mut b = Vec::new();
    b.extend_from_slice(b"RIFF");
    b.extend_from_slice(&(36 + data_len).to_le_bytes());
    b.extend_from_slice(b"WAVEfmt ");
    b.extend_from_slice(&16u32.to_le_bytes());
    b.extend_from_slice(&3u16.to_le_bytes()); // IEEE float
    b.extend_from_slice(&1u16.to_le_bytes());
    b.extend_from_slice(&16_000u32.to_le_bytes());
    b.extend_from_slice(&64_000u32.to_le_bytes());
    b.extend_from_slice(&4u16.to_le_bytes());
    b.extend_from_slice(&32u16.to_le_bytes());
    b.extend_from_slice(b"data");
    b.extend_from_slice(&data_len.to_le_bytes());
    for v in samples {
        b.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, b).unwrap();
}

#[test]
fn float_wav_with_nan_or_inf_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    for (name, bad) in [("nan.wav", f32::NAN), ("inf.wav", f32::INFINITY)] {
        let mut x = vec![0.25f32; 16_000];
        x[1234] = bad;
        let p = dir.path().join(name);
        float_wav(&p, &x);
        let e = expect_err(&p);
        assert!(e.contains("sample 1234 is not finite"), "{e}");
    }
    // A clean float WAV decodes exactly.
    let p = dir.path().join("ok.wav");
    float_wav(&p, &[0.5, -0.25, 0.125]);
    assert_eq!(
        decode_file(&p, &DecodeOptions::default()).unwrap().samples,
        vec![0.5, -0.25, 0.125]
    );
}

#[test]
fn eight_channels_mix_by_the_mean() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("eight.wav");
    // Channel k holds the constant k/16 ("dcshift" per channel via remix of a silent base is
    // awkward in sox), so generate the WAV by hand: 8 channels of 16-bit constants.
    let frames = 16_000usize;
    let mut b = Vec::new();
    let data_len = (frames * 8 * 2) as u32;
    b.extend_from_slice(b"RIFF");
    b.extend_from_slice(&(36 + data_len).to_le_bytes());
    b.extend_from_slice(b"WAVEfmt ");
    b.extend_from_slice(&16u32.to_le_bytes());
    b.extend_from_slice(&1u16.to_le_bytes());
    b.extend_from_slice(&8u16.to_le_bytes());
    b.extend_from_slice(&16_000u32.to_le_bytes());
    b.extend_from_slice(&(16_000u32 * 16).to_le_bytes());
    b.extend_from_slice(&16u16.to_le_bytes());
    b.extend_from_slice(&16u16.to_le_bytes());
    b.extend_from_slice(b"data");
    b.extend_from_slice(&data_len.to_le_bytes());
    for _ in 0..frames {
        for k in 0..8i16 {
            b.extend_from_slice(&(k * 2048).to_le_bytes());
        }
    }
    std::fs::write(&p, b).unwrap();
    let a = decode_file(&p, &DecodeOptions::default()).unwrap();
    assert_eq!(a.source_channels, 8);
    // mean of k * 2048 / 32768 for k = 0..7 = 3.5 / 16.
    assert!(
        a.samples.iter().all(|&v| (v - 3.5 / 16.0).abs() < 1e-6),
        "{}",
        a.samples[0]
    );
}

#[test]
fn high_rate_192k_is_resampled() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("hi.flac");
    tool(
        "sox",
        &[
            "-n",
            "-r",
            "192000",
            "-c",
            "2",
            "-b",
            "24",
            s(&p),
            "synth",
            "2",
            "sine",
            "1000",
            "gain",
            "-6",
        ],
    );
    let (mel, stats) = load_log_mel(&p, &DecodeOptions::default(), &MelOptions::default()).unwrap();
    assert_eq!(stats.source_rate, 192_000);
    assert_eq!(mel.shape(), &[80, 1 + 32_000 / 512]);
    // Same features as the 16 kHz rendering of the tone, away from the edges (the resampler and
    // sox's synthesis differ only by rounding): within 0.1 dB in the band holding 1 kHz.
    let p16 = dir.path().join("lo.wav");
    tool(
        "sox",
        &[
            "-n",
            "-r",
            "16000",
            "-c",
            "1",
            "-b",
            "32",
            "-e",
            "floating-point",
            s(&p16),
            "synth",
            "2",
            "sine",
            "1000",
            "gain",
            "-6",
        ],
    );
    let lo = log_mel(
        &decode_file(&p16, &DecodeOptions::default())
            .unwrap()
            .samples,
        &MelOptions::default(),
    )
    .unwrap();
    let band = (0..80)
        .max_by(|&a, &b| lo[[a, 30]].total_cmp(&lo[[b, 30]]))
        .unwrap();
    for t in 5..55 {
        assert!(
            (mel[[band, t]] - lo[[band, t]]).abs() < 0.1,
            "frame {t}: {} vs {}",
            mel[[band, t]],
            lo[[band, t]]
        );
    }
}

/// AAC in M4A: the edit list's priming/padding trim must give the source WAV's length — also for a
/// length that is not a whole number of milliseconds (the movie timescale ffmpeg writes is
/// 1000 Hz, so the kept duration is rounded to 1 ms = 44 samples there: the bound is half of
/// that, 22). ffmpeg 5.1's own `-f f32le` decode keeps the tail padding (whole 1024-frame
/// packets), so it is printed for information only.
#[test]
fn aac_in_m4a_is_trimmed_like_ffmpeg() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let src = d.join("odd.wav");
    tool(
        "sox",
        &[
            "-n",
            "-r",
            "44100",
            "-c",
            "1",
            "-b",
            "16",
            s(&src),
            "synth",
            "2.01234",
            "sine",
            "440",
            "gain",
            "-6",
        ],
    );
    let m4a = d.join("odd.m4a");
    ffmpeg(&["-i", s(&src), "-c:a", "aac", "-b:a", "128k", s(&m4a)]);
    let raw = d.join("odd.f32");
    ffmpeg(&["-i", s(&m4a), "-f", "f32le", "-ac", "1", s(&raw)]);
    let ffmpeg_len = std::fs::metadata(&raw).unwrap().len() as usize / 4;
    let ours = decode_file(&m4a, &DecodeOptions::default())
        .unwrap()
        .samples;
    let wav_len = decode_file(&src, &DecodeOptions::default())
        .unwrap()
        .samples
        .len();
    eprintln!("aac: ours {} ffmpeg {ffmpeg_len} wav {wav_len}", ours.len());
    assert!(
        ours.len().abs_diff(wav_len) <= 22,
        "ours {} vs wav {wav_len}",
        ours.len()
    );
    // Aligned: correlation with the source at lag 0 is the best among small lags.
    let src_samples = decode_file(&src, &DecodeOptions::default())
        .unwrap()
        .samples;
    let corr = |lag: isize| -> f64 {
        (10_000..60_000)
            .map(|i| f64::from(ours[i]) * f64::from(src_samples[(i as isize + lag) as usize]))
            .sum()
    };
    let best = (-50..=50)
        .max_by(|&a, &b| corr(a).total_cmp(&corr(b)))
        .unwrap();
    assert_eq!(best, 0, "AAC output shifted by {best} samples");
}

/// Hostile bytes: every format truncated at many points and with corrupted bytes decodes to a
/// result or a one-line error naming the file, never a panic or a hang.
#[test]
fn corrupted_and_truncated_files_never_panic() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let src = source_wav(d);
    let mut state = 1234u64;
    let mut rnd = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 33) as usize
    };
    for (name, codec) in [
        ("c.wav", "pcm_s16le"),
        ("c.flac", "flac"),
        ("c.mp3", "libmp3lame"),
        ("c.ogg", "libvorbis"),
        ("c.m4a", "aac"),
        ("c_alac.m4a", "alac"),
        ("c.aiff", "pcm_s16be"),
    ] {
        let full = d.join(format!("full_{name}"));
        ffmpeg(&["-i", s(&src), "-c:a", codec, s(&full)]);
        let bytes = std::fs::read(&full).unwrap();
        for k in 0..12 {
            let mut b = bytes.clone();
            if k % 2 == 0 {
                b.truncate(rnd() % b.len());
            } else {
                for _ in 0..(1 + rnd() % 50) {
                    let i = rnd() % b.len();
                    b[i] = rnd() as u8;
                }
            }
            let p = d.join(name);
            std::fs::write(&p, &b).unwrap();
            if let Err(e) = decode_file(&p, &DecodeOptions::default()) {
                let m = e.to_string();
                assert!(m.contains(name) && !m.contains('\n'), "{m}");
            }
        }
    }
}

#[test]
fn the_pull_reader_ends_with_ok_none_and_stays_there() {
    let dir = tempfile::tempdir().unwrap();
    let src = source_wav(dir.path());
    let mut r = choreo_dsp::AudioFileReader::open(&src, &DecodeOptions::default()).unwrap();
    let mut n = 0;
    while let Some(c) = r.next_chunk().unwrap() {
        assert_eq!(c.rate, 44_100);
        n += c.samples.len();
    }
    assert_eq!(n, 3 * 44_100);
    assert!(r.next_chunk().unwrap().is_none());
    assert_eq!(r.summary().frames, 3 * 44_100);
    assert_eq!(r.sample_rate(), Some(44_100));
}

/// Long MP3s are decoded as two halves on two threads; the features must be bit-identical to a
/// serial decode (the accurate seek primes the decoder, so the samples after the seam match).
#[test]
fn split_mp3_decode_equals_serial_decode() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let wav = d.join("long.wav");
    tool(
        "sox",
        &[
            "-n",
            "-r",
            "44100",
            "-c",
            "2",
            "-b",
            "16",
            s(&wav),
            "synth",
            "40",
            "sine",
            "220-3000",
            "sine",
            "1250",
            "gain",
            "-6",
        ],
    );
    let mp3 = d.join("long.mp3");
    ffmpeg(&["-i", s(&wav), "-c:a", "libmp3lame", "-b:a", "192k", s(&mp3)]);
    let serial = decode_file(&mp3, &DecodeOptions::default()).unwrap();
    assert_eq!(serial.samples.len(), 40 * 44_100);
    let y = choreo_dsp::resample_to(&serial.samples, 44_100, 16_000).unwrap();
    let want = log_mel(&y, &MelOptions::default()).unwrap();
    let (got, stats) =
        load_log_mel(&mp3, &DecodeOptions::default(), &MelOptions::default()).unwrap();
    assert_eq!(stats.duration_s, 40.0);
    assert_eq!(got.shape(), want.shape());
    let max = got
        .iter()
        .zip(want.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert_eq!(
        max, 0.0,
        "split decode differs from serial by up to {max} dB"
    );
}
