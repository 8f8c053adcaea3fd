//! The one error type of the I/O library. Every variant names the file and, where there is one,
//! the line and column at fault.

use std::path::PathBuf;
use thiserror::Error;

/// Errors reading or writing Preston's files.
#[derive(Debug, Error)]
pub enum Error {
    /// The file could not be opened, read or written.
    #[error("{}: {source}", file.display())]
    Io {
        /// The file.
        file: PathBuf,
        /// The operating-system error.
        source: std::io::Error,
    },
    /// A required column is missing from the header.
    #[error("{}: line 1: missing column `{column}` (header has: {found}){hint}", file.display())]
    MissingColumn {
        /// The file.
        file: PathBuf,
        /// The column that is required.
        column: String,
        /// The header as found.
        found: String,
        /// A suggestion (for example a column with another unit).
        hint: String,
    },
    /// A column appears twice in the header.
    #[error("{}: line 1: column `{column}` appears more than once", file.display())]
    DuplicateColumn {
        /// The file.
        file: PathBuf,
        /// The repeated column.
        column: String,
    },
    /// A cell could not be used.
    #[error("{}: line {line}, column `{column}`: {why}", file.display())]
    Cell {
        /// The file.
        file: PathBuf,
        /// 1-based line number (the header is line 1).
        line: u64,
        /// The column name.
        column: String,
        /// What is wrong with the cell.
        why: String,
    },
    /// The CSV structure itself is broken (unequal field counts, bad UTF-8, ...).
    #[error("{}: line {line}: {why}", file.display())]
    Csv {
        /// The file.
        file: PathBuf,
        /// 1-based line number.
        line: u64,
        /// The parser's message.
        why: String,
    },
    /// The file holds no data rows (or no usable ones).
    #[error("{}: {why}", file.display())]
    Empty {
        /// The file.
        file: PathBuf,
        /// What was missing.
        why: String,
    },
    /// Two rows give the same point.
    #[error("{}: line {line} repeats the point ({x_mm}, {y_mm}) mm of line {first_line}", file.display())]
    DuplicatePoint {
        /// The file.
        file: PathBuf,
        /// The line of the repeat.
        line: u64,
        /// The line where the point first appears.
        first_line: u64,
        /// x of the point, mm.
        x_mm: f64,
        /// y of the point, mm.
        y_mm: f64,
    },
    /// A job file could not be parsed (unknown keys, wrong types, missing fields).
    #[error("{}: {why}", file.display())]
    Job {
        /// The job file.
        file: PathBuf,
        /// The parser's message (names the key and line).
        why: String,
    },
    /// A JSON document could not be parsed or written.
    #[error("{}: {why}", file.display())]
    Json {
        /// The file.
        file: PathBuf,
        /// The parser's message.
        why: String,
    },
    /// The data were read but the engine rejected them.
    #[error("{}: {source}", file.display())]
    Engine {
        /// The file the data came from.
        file: PathBuf,
        /// The engine's error.
        source: preston_solver::Error,
    },
    /// A binary file (instrument data, HDF5, NPY) is malformed or truncated: where, and why.
    #[error("{}: {at}: {why}", file.display())]
    Binary {
        /// The file.
        file: PathBuf,
        /// Where in the file: a byte offset, a header field or an HDF5 object path.
        at: String,
        /// What is wrong (never the file's bytes).
        why: String,
    },
    /// A command-line or job option could not be used.
    #[error("{option}: {why}")]
    Option {
        /// The option (`--aperture`, `[map] columns`, ...).
        option: String,
        /// Why it was rejected.
        why: String,
    },
    /// An output that is written only where nothing is yet exists already.
    #[error("{}: already exists; {why}", file.display())]
    Exists {
        /// The existing file.
        file: PathBuf,
        /// How to write over it.
        why: String,
    },
    /// An engine error not tied to one file.
    #[error(transparent)]
    Solver(#[from] preston_solver::Error),
}

/// Result alias of the I/O library.
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// Wraps an engine error with the file its data came from.
    pub fn engine(file: impl Into<PathBuf>, source: preston_solver::Error) -> Self {
        Error::Engine {
            file: file.into(),
            source,
        }
    }

    /// A malformed binary file: `at` names the offset, field or object.
    pub fn binary(file: impl Into<PathBuf>, at: impl Into<String>, why: impl Into<String>) -> Self {
        Error::Binary {
            file: file.into(),
            at: at.into(),
            why: why.into(),
        }
    }

    /// A rejected option.
    pub fn option(option: impl Into<String>, why: impl Into<String>) -> Self {
        Error::Option {
            option: option.into(),
            why: why.into(),
        }
    }

    /// Wraps an OS error with its file.
    pub fn io(file: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            file: file.into(),
            source,
        }
    }
}
