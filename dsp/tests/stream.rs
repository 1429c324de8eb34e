//! Streaming equals offline: any chunking of the input gives bit-identical frames, at the
//! analysis rate and through the internal resampler.

// Helpers outside #[test] fns are test code too: a panic there is a failed test.
#![allow(clippy::unwrap_used)]

mod common;

use choreo_dsp::{FeatureStream, LogMelStream, MelOptions, clamp_top_db, log_mel, resample_to};
use common::{read_npy_f32, reference};
use ndarray::Array2;

/// Run a stream over `x` (at `rate`) in the given chunk sizes (cycled), reading and discarding
/// frames as they become ready the way a live consumer would. Returns (T, n_mels) frames.
fn run_stream(x: &[f32], rate: u32, chunks: &[usize]) -> Array2<f32> {
    let opts = MelOptions::default();
    let mut s = LogMelStream::new(&opts).unwrap();
    let mut got: Vec<f32> = Vec::new();
    let mut read = 0usize;
    let mut pos = 0usize;
    let mut i = 0usize;
    let drain = |s: &mut LogMelStream, read: &mut usize, got: &mut Vec<f32>| {
        let ready = s.frames_ready();
        if ready > *read {
            got.extend(s.frames(*read, ready - *read).unwrap().iter());
            *read = ready;
            s.discard_frames_before(*read);
            assert!(
                s.frames(0, 1).is_err() || *read == 0,
                "discarded frames must be gone"
            );
        }
    };
    while pos < x.len() {
        let n = chunks[i % chunks.len()].min(x.len() - pos);
        s.accept_waveform(rate, &x[pos..pos + n]).unwrap();
        pos += n;
        i += 1;
        drain(&mut s, &mut read, &mut got);
    }
    s.input_finished().unwrap();
    drain(&mut s, &mut read, &mut got);
    assert!(s.is_last_frame(read - 1));
    Array2::from_shape_vec((read, 80), got).unwrap()
}

fn lcg_sizes(seed: u64, n: usize, max: usize) -> Vec<usize> {
    let mut state = seed;
    (0..n)
        .map(|_| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            1 + (state >> 33) as usize % max
        })
        .collect()
}

#[test]
fn chunked_feeding_is_bit_identical_to_one_shot_at_16k() {
    let (_, y) = read_npy_f32(&reference("vibe_ace_22k_mono", "wav16k.npy"));
    let y = &y[..16_000 * 6];
    let whole = run_stream(y, 16_000, &[y.len()]);
    for chunks in [vec![1usize], vec![17], vec![4096], lcg_sizes(7, 1000, 3000)] {
        let got = run_stream(y, 16_000, &chunks);
        assert_eq!(got, whole, "chunks {:?}", &chunks[..chunks.len().min(3)]);
    }
    // The stream does not clamp; offline = stream + the global top_db clamp.
    let mut clamped = whole.t().as_standard_layout().into_owned();
    clamp_top_db(clamped.as_slice_mut().unwrap(), 80.0);
    assert_eq!(clamped, log_mel(y, &MelOptions::default()).unwrap());
}

#[test]
fn chunked_feeding_through_the_resampler_is_bit_identical() {
    // 44.1 kHz input: the stream resamples inside.
    let x: Vec<f32> = (0..44_100 * 4)
        .map(|i| {
            let t = i as f32 / 44_100.0;
            0.5 * (2.0 * std::f32::consts::PI * 440.0 * t).sin()
                + 0.2 * (2.0 * std::f32::consts::PI * 3100.0 * t).sin()
        })
        .collect();
    let whole = run_stream(&x, 44_100, &[x.len()]);
    for chunks in [vec![17usize], vec![4096], lcg_sizes(11, 500, 5000)] {
        assert_eq!(run_stream(&x, 44_100, &chunks), whole);
    }
    // Same as resampling first and analysing at 16 kHz.
    let y = resample_to(&x, 44_100, 16_000).unwrap();
    assert_eq!(run_stream(&y, 16_000, &[y.len()]), whole);
}

#[test]
fn rate_change_and_input_after_finish_are_errors() {
    let mut s = LogMelStream::new(&MelOptions::default()).unwrap();
    s.accept_waveform(48_000, &[0.0; 480]).unwrap();
    let e = s.accept_waveform(44_100, &[0.0; 441]).unwrap_err();
    assert!(e.to_string().contains("48000 Hz to 44100 Hz"), "{e}");
    s.input_finished().unwrap();
    assert!(s.accept_waveform(48_000, &[0.0; 10]).is_err());
    // Frames not ready yet are an error, not a panic.
    assert!(s.frames(0, s.frames_ready() + 1).is_err());
}

#[test]
fn memory_stays_bounded_while_streaming() {
    // 10 minutes of input in 1 s chunks with frames consumed as they come: the held frames stay
    // at a handful (the consumer discards) — checked through the public frame window.
    let mut s = LogMelStream::new(&MelOptions::default()).unwrap();
    let chunk = vec![0.1f32; 16_000];
    let mut read = 0;
    for _ in 0..600 {
        s.accept_waveform(16_000, &chunk).unwrap();
        read = s.frames_ready();
        s.discard_frames_before(read);
        assert!(s.frames(read.saturating_sub(1), 1).is_err() || read == 0);
        let (samples, values) = s.held();
        // At most ~4 FFT windows of input plus one chunk are kept (buffer compaction
        // granularity), and no frames after discarding.
        assert!(
            samples <= 4 * 2048 + 16_000 + 2048,
            "{samples} samples held"
        );
        assert_eq!(values, 0);
    }
    assert_eq!(read, (600 * 16_000 - 1024) / 512 + 1);
}

#[test]
fn threaded_offline_path_equals_the_stream_on_a_long_signal() {
    // 1921 frames: the offline path splits them over threads; every frame must still be
    // bit-identical to the single stream's (then clamped the same way).
    let (_, y) = read_npy_f32(&reference("vibe_ace_44k_stereo", "wav16k.npy"));
    let streamed = run_stream(&y, 16_000, &[4096]);
    let mut clamped = streamed.t().as_standard_layout().into_owned();
    clamp_top_db(clamped.as_slice_mut().unwrap(), 80.0);
    assert_eq!(clamped, log_mel(&y, &MelOptions::default()).unwrap());
}

#[test]
fn the_stream_does_not_clamp_but_offline_clamps_against_the_global_max() {
    // 1 s of a loud tone, then 1 s of digital silence.
    let mut x: Vec<f32> = (0..16_000)
        .map(|i| 0.8 * (2.0 * std::f32::consts::PI * 500.0 * i as f32 / 16_000.0).sin())
        .collect();
    x.extend(std::iter::repeat_n(0.0, 16_000));
    let streamed = run_stream(&x, 16_000, &[1000]);
    let offline = log_mel(&x, &MelOptions::default()).unwrap();
    let max = offline.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let last = streamed.nrows() - 1;
    // Documented choice: stream frames are plain power_to_db, floored only by amin (-100 dB)...
    assert!(streamed.row(last).iter().all(|&v| v == -100.0));
    // ...while offline clamps at max - top_db, as librosa does.
    assert!(offline.column(last).iter().all(|&v| v == max - 80.0));
}
