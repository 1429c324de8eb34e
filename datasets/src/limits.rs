//! Reader limits: every reader of this crate (`.npy`, `.pkl`, `.bvh`, `.h5`) bounds what it
//! allocates by what the file can actually hold and by one element cap, checked before
//! allocating. The cap is process-wide so every reader obeys the same number; `choreod` sets it
//! from `--max-elements`.

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
}
