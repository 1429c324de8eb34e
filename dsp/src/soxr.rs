//! librosa 0.10's default resampler, `res_type="soxr_hq"` (`librosa:core/audio.py` `resample`
//! → python-soxr `resample(y, orig_sr, target_sr, quality="soxr_hq")`), through the system's
//! libsoxr (LGPL, linked dynamically; Debian's `libsoxr-dev`): `soxr_oneshot` with the HQ recipe
//! (`soxr_quality_spec(SOXR_HQ, 0)`: 20-bit precision), float32 in and out, default run-time
//! settings. python-soxr 1.1.0's bundled libsoxr and Debian's libsoxr 0.1.3 give bit-identical
//! output for the same call (checked on noise and on the golden fixtures: `tests/fact35.rs`).
//!
//! The binding is these two functions (`/usr/include/soxr.h`), written here rather than taken
//! from the `libsoxr` crates, which are LGPL and would be compiled into the binary.

use std::ffi::{CStr, c_char, c_uint, c_ulong, c_void};

use crate::error::{Error, Result};
use crate::kaiser::{librosa_resample_len, too_short_to_resample};

/// `struct soxr_quality_spec` (soxr.h 0.1.3).
#[repr(C)]
struct QualitySpec {
    precision: f64,
    phase_response: f64,
    passband_end: f64,
    stopband_begin: f64,
    e: *mut c_void,
    flags: c_ulong,
}

/// `SOXR_HQ` = `SOXR_20_BITQ` (soxr.h).
const SOXR_HQ: c_ulong = 4;

#[allow(unsafe_code)]
#[link(name = "soxr")]
unsafe extern "C" {
    fn soxr_quality_spec(recipe: c_ulong, flags: c_ulong) -> QualitySpec;
    #[allow(clippy::too_many_arguments)]
    fn soxr_oneshot(
        input_rate: f64,
        output_rate: f64,
        num_channels: c_uint,
        input: *const c_void,
        ilen: usize,
        idone: *mut usize,
        output: *mut c_void,
        olen: usize,
        odone: *mut usize,
        io_spec: *const c_void,
        quality_spec: *const QualitySpec,
        runtime_spec: *const c_void,
    ) -> *const c_char;
}

/// `librosa.resample(y, orig_sr, target_sr, res_type="soxr_hq", fix=True, scale)`: soxr's
/// output zero-padded or cut to `ceil(len × ratio)`, divided by `sqrt(ratio)` (in float32, as
/// numpy divides a float32 array by a scalar) when `scale`. Equal rates return a copy.
///
/// Errors: a non-positive or non-finite rate, an input too short to yield one sample, or
/// libsoxr failing.
pub fn resample_soxr_hq(y: &[f32], orig_sr: f64, target_sr: f64, scale: bool) -> Result<Vec<f32>> {
    if orig_sr == target_sr && orig_sr > 0.0 && orig_sr.is_finite() {
        return Ok(y.to_vec());
    }
    let (ratio, n_fixed) = librosa_resample_len(y.len(), orig_sr, target_sr)?;
    if n_fixed < 1 {
        return Err(too_short_to_resample(y.len()));
    }
    // soxr yields about len × ratio samples; the margin takes its rounding.
    let mut out = vec![0.0f32; n_fixed + 64];
    let mut odone = 0usize;
    // SAFETY: `y` and `out` are live slices of f32 (the default io spec is float32 in and out,
    // one channel) whose lengths are passed alongside; soxr writes at most `out.len()` samples
    // and `odone` before returning; the quality spec is a value libsoxr itself made; null io
    // and run-time specs select libsoxr's documented defaults; the error is null or a static
    // string.
    #[allow(unsafe_code)]
    let error = unsafe {
        let quality = soxr_quality_spec(SOXR_HQ, 0);
        let error = soxr_oneshot(
            orig_sr,
            target_sr,
            1,
            y.as_ptr().cast(),
            y.len(),
            std::ptr::null_mut(),
            out.as_mut_ptr().cast(),
            out.len(),
            &mut odone,
            std::ptr::null(),
            &quality,
            std::ptr::null(),
        );
        (!error.is_null()).then(|| CStr::from_ptr(error).to_string_lossy().into_owned())
    };
    if let Some(reason) = error {
        return Err(Error::Resample {
            from: orig_sr as u32,
            to: target_sr as u32,
            reason,
        });
    }
    out.truncate(odone.min(out.len()));
    out.resize(n_fixed, 0.0);
    if scale {
        let s = ratio.sqrt() as f32;
        for v in &mut out {
            *v /= s;
        }
    }
    Ok(out)
}
#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sine_keeps_its_frequency_and_level_and_the_length_is_librosas() {
        let sr = 44_100.0;
        let x: Vec<f32> = (0..44_100)
            .map(|i| (2.0 * std::f64::consts::PI * 440.0 * f64::from(i) / sr).sin() as f32)
            .collect();
        let y = resample_soxr_hq(&x, sr, 15_360.0, false).unwrap();
        assert_eq!(y.len(), 15_360);
        // Away from the edges the output is the same sine sampled at the new rate (HQ's
        // 20-bit precision: ~1e-5 of full scale).
        let worst = (1000..14_000)
            .map(|i| {
                let want = (2.0 * std::f64::consts::PI * 440.0 * i as f64 / 15_360.0).sin();
                (f64::from(y[i]) - want).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < 1e-4, "{worst}");
        let halved = resample_soxr_hq(&x, 2.0, 1.0, true).unwrap();
        assert_eq!(halved.len(), 22_050);
    }

    #[test]
    fn bad_rates_and_empty_input_are_errors() {
        assert!(resample_soxr_hq(&[0.0; 10], 0.0, 1.0, false).is_err());
        assert!(resample_soxr_hq(&[0.0; 10], 1.0, f64::NAN, false).is_err());
        assert!(resample_soxr_hq(&[], 2.0, 1.0, false).is_err());
    }
}
