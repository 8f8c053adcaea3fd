//! The memory budget: every size that an argument or a file header implies (grids, samples per
//! point, lattices, paths, operators, dense matrices) is turned into bytes and checked here
//! before anything is allocated, so an oversized request is refused with a message naming the
//! argument, the size it implies and the limit, instead of aborting the process.
//!
//! The limit is process-wide: [`DEFAULT_LIMIT_BYTES`] (8 GiB), or half the physical memory where
//! that is less (Linux: `MemTotal` of `/proc/meminfo`), unless [`set_limit_bytes`] changes it
//! (the command line's `--max-memory-gb`). Estimates count the dominant arrays only (8 bytes
//! per `f64`), so they are lower bounds of the true peak; the limit is a guard against
//! requests that are wrong by orders of magnitude, not an exact accountant.

use crate::error::{Error, Result};
use std::sync::atomic::{AtomicU64, Ordering};

/// The default limit where physical memory is at least twice as much: 8 GiB.
pub const DEFAULT_LIMIT_BYTES: u64 = 8 << 30;

/// Bytes per `f64`.
pub const F64_BYTES: f64 = 8.0;

/// 0: not set yet (the default applies).
static LIMIT_BYTES: AtomicU64 = AtomicU64::new(0);

/// Sets the process-wide limit in bytes.
pub fn set_limit_bytes(bytes: u64) {
    LIMIT_BYTES.store(bytes.max(1), Ordering::Relaxed);
}

/// The process-wide limit in bytes.
pub fn limit_bytes() -> u64 {
    match LIMIT_BYTES.load(Ordering::Relaxed) {
        0 => default_limit_bytes(),
        b => b,
    }
}

/// [`DEFAULT_LIMIT_BYTES`], or half the physical memory where that is less.
pub fn default_limit_bytes() -> u64 {
    static DEFAULT: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *DEFAULT.get_or_init(|| {
        physical_memory_bytes().map_or(DEFAULT_LIMIT_BYTES, |m| DEFAULT_LIMIT_BYTES.min(m / 2))
    })
}

/// Physical memory (Linux: `MemTotal` of `/proc/meminfo`); `None` where unknown.
fn physical_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib.saturating_mul(1024))
}

/// Formats a byte count in GB (10^9 bytes), or in MB below 0.1 GB.
pub fn format_bytes(bytes: f64) -> String {
    if !bytes.is_finite() {
        "an unbounded amount".into()
    } else if bytes >= 1e8 {
        format!("{:.3} GB", bytes / 1e9)
    } else {
        format!("{:.1} MB", bytes / 1e6)
    }
}

/// Checks that `bytes` (computed in floating point, so that no product overflows) fits in the
/// limit. `what` names the argument or file field responsible (`--samples-per-point`) and
/// `detail` how the size follows from it (`4e9 samples x 3 arrays`).
pub fn check(what: &str, detail: &str, bytes: f64) -> Result<()> {
    let limit = limit_bytes();
    if bytes.is_finite() && bytes <= limit as f64 {
        return Ok(());
    }
    Err(Error::invalid(
        what,
        format!(
            "{detail} needs {} of memory, over the limit of {} (raise it with --max-memory-gb)",
            format_bytes(bytes),
            format_bytes(limit as f64)
        ),
    ))
}

/// Checks `count` values of `arrays` `f64` arrays each: `count * arrays * 8` bytes.
pub fn check_f64s(what: &str, detail: &str, count: f64, arrays: f64) -> Result<()> {
    check(what, detail, count * arrays * F64_BYTES)
}

/// `len` copies of `value` in a new vector, or an error naming `what` when the memory cannot be
/// had (`Vec::try_reserve_exact`: an address-space cap or a refused mapping ends in an error, not
/// in an abort). For the buffers whose size the inputs imply after [`check`] let them through.
pub fn try_filled<T: Clone>(what: &str, len: usize, value: T) -> Result<Vec<T>> {
    let mut v = Vec::new();
    v.try_reserve_exact(len).map_err(|_| {
        Error::invalid(
            what,
            format!(
                "{} of memory ({len} values) could not be allocated (lower --max-memory-gb to be \
                 told before a solve starts, or reduce the problem)",
                format_bytes(len as f64 * std::mem::size_of::<T>() as f64)
            ),
        )
    })?;
    v.resize(len, value);
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The limit is process-wide, so the tests run in one function to avoid races.
    #[test]
    fn refuses_over_the_limit_and_names_the_argument() {
        assert!(check("--x", "1 value", 8.0).is_ok());
        let e = check("--grid", "1e10 points x 2 arrays", 1.6e11)
            .unwrap_err()
            .to_string();
        assert!(e.contains("--grid") && e.contains("160.000 GB"), "{e}");
        assert!(limit_bytes() <= DEFAULT_LIMIT_BYTES && limit_bytes() > 0);
        assert!(check("--x", "inf", f64::INFINITY).is_err());
        assert!(check("--x", "nan", f64::NAN).is_err());
        // Exactly the limit passes; one byte more does not.
        let lim = limit_bytes() as f64;
        assert!(check("--x", "", lim).is_ok());
        assert!(check("--x", "", lim + 1024.0).is_err());
        assert!(check_f64s("--x", "", lim / 16.0, 2.0).is_ok());
        assert!(check_f64s("--x", "", lim / 16.0, 3.0).is_err());
    }

    /// A buffer that can be had is filled; one that cannot (more than the address space) is an
    /// error naming what it was for, not an abort.
    #[test]
    fn allocation_that_cannot_be_had_is_an_error() {
        assert_eq!(try_filled("lattice", 3, 1.5).unwrap(), vec![1.5; 3]);
        assert!(try_filled::<f64>("lattice", 0, 0.0).unwrap().is_empty());
        let e = try_filled("FFT lattice", usize::MAX / 16, 0.0f64)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("FFT lattice") && e.contains("could not be allocated"),
            "{e}"
        );
    }
}
