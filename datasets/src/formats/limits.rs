//! Reader limits: every reader of this crate (`.npy`, `.pkl`, `.bvh`, `.h5`) bounds what it
//! allocates by what the file can actually hold and by one element cap, checked before
//! allocating. The cap is process-wide so every reader obeys the same number; the program sets
//! it ([`set_max_elements`]). Frame rates, read from files or given by flags, lie in [`FPS_RANGE`],
//! and what a change of rate makes is checked against the cap before it is allocated
//! ([`resampled_frames`]).

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::error::{Error, Result};

/// Default cap on the values one file may make a reader hold: 2^27 (512 MiB as f32). The
/// largest real inputs are far below it: a 10-minute AIST++ take is 36,000 × 72 poses (2.6 M),
/// a 20-minute dance at 30 fps 2.6 M joint values, HumanML3D's longest clip 24,000 × 263 (6.3 M).
pub const DEFAULT_MAX_ELEMENTS: usize = 1 << 27;

static MAX_ELEMENTS: AtomicUsize = AtomicUsize::new(DEFAULT_MAX_ELEMENTS);

/// Set the element cap of every reader (process-wide).
pub fn set_max_elements(n: usize) {
    MAX_ELEMENTS.store(n, Ordering::Relaxed);
}

/// The current element cap.
pub fn max_elements() -> usize {
    MAX_ELEMENTS.load(Ordering::Relaxed)
}

/// Frame rates accepted for motion, in frames per second, wherever they come from (a BVH's
/// `Frame Time`, an `.h5`'s `/motion` fps, a package's `motion.fps`, `--fps`, `--bas-fps`):
/// from keyframed clips at 1 fps to high-speed optical capture at 1000 Hz. Outside it a rate is
/// a corrupt or hostile value: resampling a motion at 1e-4 fps to 20 fps would make 200,000
/// frames of every one.
pub const FPS_RANGE: std::ops::RangeInclusive<f32> = 1.0..=1000.0;

/// `Err(reason)` unless `fps` lies in [`FPS_RANGE`]; the reason reads after the value's name,
/// e.g. "/motion fps: 0.0001 fps is outside ...".
pub fn check_fps(fps: f32) -> std::result::Result<f32, String> {
    if FPS_RANGE.contains(&fps) {
        Ok(fps)
    } else {
        Err(format!(
            "{fps} fps is outside the accepted {}..={} fps",
            FPS_RANGE.start(),
            FPS_RANGE.end()
        ))
    }
}

/// Frames a motion of `frames` frames has after resampling from `from_fps` to `to_fps` (its
/// duration × the new rate: `floor((frames - 1) · to / from) + 1`), refused as a reason when
/// the result would hold more than the element cap with `values_per_frame` values per frame
/// ([`Error::ResampleTooLarge`], without a path). Computed in f64 before anything is allocated.
pub(crate) fn resampled_frames(
    frames: usize,
    values_per_frame: usize,
    from_fps: f32,
    to_fps: f32,
) -> Result<usize> {
    if frames == 0 {
        return Ok(0);
    }
    // The same expression as the resampler's loop bound, so the two always agree.
    let ratio = f64::from(from_fps) / f64::from(to_fps);
    let out = ((frames - 1) as f64 / ratio).floor() + 1.0;
    let values = out * values_per_frame as f64;
    let limit = max_elements();
    if values > limit as f64 {
        return Err(Error::ResampleTooLarge {
            path: None,
            frames,
            from_fps,
            to_fps,
            // Saturates for absurd rates: the message only has to say "too many".
            resampled: out as u64,
            values_per_frame,
            limit,
        });
    }
    Ok(out as usize)
}

/// The number of values of `shape`, refused ([`Error::TooLarge`]) when it overflows or exceeds
/// the cap. `what` names the array in the message.
pub(crate) fn elements(path: &Path, what: &str, shape: &[usize]) -> Result<usize> {
    let n = shape.iter().try_fold(1usize, |a, d| a.checked_mul(*d));
    let limit = max_elements();
    match n {
        Some(n) if n <= limit => Ok(n),
        _ => Err(Error::TooLarge {
            path: path.to_path_buf(),
            what: format!("{what} of shape {shape:?}"),
            limit,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn products_over_the_cap_or_overflowing_are_refused() {
        let p = Path::new("x.npy");
        assert_eq!(elements(p, "a", &[2, 3]).unwrap(), 6);
        assert_eq!(elements(p, "a", &[]).unwrap(), 1);
        let e = elements(p, "a", &[DEFAULT_MAX_ELEMENTS, 2]).unwrap_err();
        assert!(matches!(e, Error::TooLarge { .. }), "{e}");
        assert!(elements(p, "a", &[usize::MAX, 2]).is_err());
    }

    #[test]
    fn resampled_sizes_are_duration_times_rate_and_capped() {
        // 721 frames at 60 fps are 12 s: 241 frames at 20, 361 at 30, 1441 at 120.
        assert_eq!(resampled_frames(721, 72, 60.0, 20.0).unwrap(), 241);
        assert_eq!(resampled_frames(721, 72, 60.0, 30.0).unwrap(), 361);
        assert_eq!(resampled_frames(721, 72, 60.0, 120.0).unwrap(), 1441);
        assert_eq!(resampled_frames(0, 72, 60.0, 120.0).unwrap(), 0);
        // A million frames at 1 fps drawn at 512 fps (ratios of powers of two are exact).
        let e = resampled_frames(1_000_000, 72, 1.0, 512.0).unwrap_err();
        assert!(
            matches!(
                e,
                Error::ResampleTooLarge {
                    resampled: 511_999_489,
                    values_per_frame: 72,
                    ..
                }
            ),
            "{e}"
        );
        assert!(resampled_frames(10, 72, 1.0, f32::MAX).is_err());
    }

    #[test]
    fn frame_rates_outside_the_range_are_refused() {
        for ok in [1.0, 20.0, 30000.0 / 1001.0, 1000.0] {
            assert_eq!(check_fps(ok), Ok(ok));
        }
        for bad in [
            0.0,
            0.9999,
            1e-4,
            1000.001,
            1e9,
            f32::NAN,
            f32::INFINITY,
            -30.0,
        ] {
            assert!(check_fps(bad).is_err(), "{bad}");
        }
    }
}
