//! The one error type of the engine library.

use thiserror::Error;

/// Everything the engine can reject. Messages name the quantity, point or index at fault.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum Error {
    /// An input value is outside its valid range (for example a non-positive feed limit).
    #[error("invalid {what}: {why}")]
    InvalidInput {
        /// The quantity at fault, with its unit (for example `v_max_mm_per_min`).
        what: String,
        /// Why it was rejected.
        why: String,
    },
    /// A point carries a non-finite coordinate or value.
    #[error("{what} point {index} is not finite ({detail})")]
    NonFinite {
        /// Which set of points (map, dwell, TIF, ...).
        what: &'static str,
        /// Zero-based index of the point.
        index: usize,
        /// The offending values.
        detail: String,
    },
    /// Array lengths that must agree do not.
    #[error("length mismatch: {what} has {got} entries, expected {expected}")]
    LengthMismatch {
        /// What was being checked.
        what: &'static str,
        /// Length supplied.
        got: usize,
        /// Length required.
        expected: usize,
    },
    /// Samples that must lie on a regular grid do not.
    #[error("{what} is not on a regular grid: {why}")]
    NotRegularGrid {
        /// Which data (for example the TIF).
        what: &'static str,
        /// Which sample or spacing broke the grid.
        why: String,
    },
    /// A geometric computation has no valid answer (outside the surface's domain, degenerate points).
    #[error("geometry: {0}")]
    Geometry(String),
    /// A G-code program cannot be read or written as asked; `line` is 1-based (0: the whole
    /// program).
    #[error("program line {line}: {why}")]
    Program {
        /// Line of the program text at fault (0 when no line applies).
        line: usize,
        /// What is wrong with it.
        why: String,
    },
    /// The numerical back end failed outright (not the same as not converging, which is a status).
    #[error("numerical failure in {stage}: {why}")]
    Numerical {
        /// The stage that failed (assembly, QP set-up, factorisation, ...).
        stage: &'static str,
        /// What the back end reported.
        why: String,
    },
    /// The caller asked for the work to stop ([`crate::observer::Observer::cancelled`]) and it
    /// stopped before finishing: there is no result.
    #[error("cancelled before finishing")]
    Cancelled,
}

/// Result alias of the engine library.
pub type Result<T> = std::result::Result<T, Error>;

/// `v` rounded to 12 significant figures, for messages: a pitch found from differences of
/// coordinates then reads as the instrument wrote it (0.2, not 0.1999999999999993).
pub(crate) fn twelve_figures(v: f64) -> f64 {
    format!("{v:.11e}").parse().unwrap_or(v)
}

impl Error {
    /// Shorthand for [`Error::InvalidInput`].
    pub fn invalid(what: impl Into<String>, why: impl Into<String>) -> Self {
        Error::InvalidInput {
            what: what.into(),
            why: why.into(),
        }
    }

    /// Checks that every named value is finite and positive; the first that is not gives
    /// `InvalidInput` naming it ("must be positive, got v").
    pub fn require_positive(values: &[(&str, f64)]) -> Result<()> {
        match values.iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            Some((name, v)) => Err(Error::invalid(*name, format!("must be positive, got {v}"))),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::twelve_figures;

    /// Differences of decimal coordinates read as written; numbers with 12 or fewer significant
    /// figures are unchanged.
    #[test]
    fn twelve_figures_undoes_the_rounding_of_differences() {
        assert_ne!(0.6 - 0.4, 0.2);
        assert_eq!(twelve_figures(0.6 - 0.4), 0.2);
        assert_eq!(twelve_figures(0.1999999999999993), 0.2);
        assert_eq!(twelve_figures(1000.36 - 1000.0).to_string(), "0.36");
        for v in [0.36, 1234.5678, -7.25e-5, 0.0, 118.0] {
            assert_eq!(twelve_figures(v), v);
        }
    }
}
