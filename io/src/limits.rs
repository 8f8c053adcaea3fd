//! Limits on what the readers accept, so that a hostile or mistaken file costs little memory and
//! a short message: a maximum line length and field count for text files (process-wide,
//! overridable: the command line's `--max-line-bytes` and `--max-fields`), regular files only
//! (never a directory, a device such as `/dev/zero` or a FIFO), at most [`QUOTE_CHARS`]
//! characters of the input quoted in a message, and the physical ranges of the model's
//! quantities (beyond them a value is an input error naming its line, not a number for the
//! solver to overflow on).

use crate::error::{Error, Result};
use std::fs::File;
use std::io::{BufRead, Read};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

/// Default maximum length of one line of a text input: 1 MiB.
pub const DEFAULT_MAX_LINE_BYTES: u64 = 1 << 20;
/// Default maximum number of fields in one line of a delimited text input.
pub const DEFAULT_MAX_FIELDS: u64 = 1000;
/// Largest job, surface or JSON file read whole: 16 MiB (they are a few kB).
pub const MAX_DOCUMENT_BYTES: u64 = 16 << 20;
/// Most characters of the input quoted in an error message.
pub const QUOTE_CHARS: usize = 80;

/// Largest |x|, |y| (and sag) accepted, mm: 100 m.
pub const MAX_ABS_COORDINATE_MM: f64 = 1e5;
/// Largest |height| accepted, nm: 10 mm.
pub const MAX_ABS_HEIGHT_NM: f64 = 1e7;
/// Largest |removal rate| accepted, nm/s: 10 mm/s.
pub const MAX_ABS_RATE_NM_PER_S: f64 = 1e7;
/// Largest dwell time accepted, s: about three years.
pub const MAX_DWELL_S: f64 = 1e8;

static MAX_LINE_BYTES: AtomicU64 = AtomicU64::new(DEFAULT_MAX_LINE_BYTES);
static MAX_FIELDS: AtomicU64 = AtomicU64::new(DEFAULT_MAX_FIELDS);

/// Sets the process-wide maximum line length, bytes.
pub fn set_max_line_bytes(n: u64) {
    MAX_LINE_BYTES.store(n.max(1), Ordering::Relaxed);
}

/// The process-wide maximum line length, bytes.
pub fn max_line_bytes() -> u64 {
    MAX_LINE_BYTES.load(Ordering::Relaxed)
}

/// Sets the process-wide maximum field count per line.
pub fn set_max_fields(n: u64) {
    MAX_FIELDS.store(n.max(1), Ordering::Relaxed);
}

/// The process-wide maximum field count per line.
pub fn max_fields() -> u64 {
    MAX_FIELDS.load(Ordering::Relaxed)
}

/// At most [`QUOTE_CHARS`] characters of `s`, with `...` when cut.
pub fn quote(s: &str) -> String {
    if s.chars().count() > QUOTE_CHARS {
        format!("{}...", s.chars().take(QUOTE_CHARS).collect::<String>())
    } else {
        s.to_string()
    }
}

/// A parser's message with every line cut to [`QUOTE_CHARS`] characters and at most 20 lines
/// (parsers such as TOML's quote the offending line whole).
pub fn quote_message(s: &str) -> String {
    let mut out: Vec<String> = s.lines().take(20).map(quote).collect();
    if s.lines().count() > 20 {
        out.push("...".into());
    }
    out.join("\n")
}

/// What kind of non-regular file `meta` describes.
fn kind(meta: &std::fs::Metadata) -> &'static str {
    let t = meta.file_type();
    if t.is_dir() {
        return "a directory";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_char_device() || t.is_block_device() {
            return "a device";
        }
        if t.is_fifo() {
            return "a FIFO (named pipe)";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    "not a regular file"
}

fn not_regular(path: &Path, meta: &std::fs::Metadata) -> Error {
    Error::io(
        path,
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("is {}; an input must be a regular file", kind(meta)),
        ),
    )
}

/// Opens `path` for reading if it is a regular file (checked before opening, so that a FIFO does
/// not block, and again on the open file).
pub fn open_regular(path: &Path) -> Result<File> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if !meta.is_file() {
        return Err(not_regular(path, &meta));
    }
    let f = File::open(path).map_err(|e| Error::io(path, e))?;
    let meta = f.metadata().map_err(|e| Error::io(path, e))?;
    if !meta.is_file() {
        return Err(not_regular(path, &meta));
    }
    Ok(f)
}

/// Reads a whole regular file of at most `max_bytes` bytes (`what` names the limit in the
/// message).
pub fn read_regular(path: &Path, max_bytes: u64, what: &str) -> Result<Vec<u8>> {
    let f = open_regular(path)?;
    let len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    if len > max_bytes {
        return Err(Error::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!(
                    "{len} bytes, more than the {max_bytes} bytes a {what} may have; is this the \
                     right file?"
                ),
            ),
        ));
    }
    let mut out = Vec::with_capacity(len as usize);
    f.take(max_bytes + 1)
        .read_to_end(&mut out)
        .map_err(|e| Error::io(path, e))?;
    Ok(out)
}

/// Reads a whole regular text file (job, surface, JSON) of at most [`MAX_DOCUMENT_BYTES`]
/// whose lines are all within the line limit. A leading UTF-8 byte-order mark (as some
/// editors write) is dropped, as every table reader drops it.
pub fn read_document(path: &Path, what: &str) -> Result<String> {
    let bytes = read_regular(path, MAX_DOCUMENT_BYTES, what)?;
    let max = max_line_bytes() as usize;
    if let Some((k, _)) = bytes
        .split(|&b| b == b'\n')
        .enumerate()
        .find(|(_, l)| l.len() > max)
    {
        return Err(line_too_long(path, k as u64 + 1, max as u64));
    }
    let mut text = String::from_utf8(bytes).map_err(|e| Error::Csv {
        file: path.to_path_buf(),
        line: 0,
        why: format!("not valid UTF-8 ({e})"),
    })?;
    if text.starts_with('\u{feff}') {
        text.drain(..'\u{feff}'.len_utf8());
    }
    Ok(text)
}

fn line_too_long(path: &Path, line: u64, max: u64) -> Error {
    Error::Csv {
        file: path.to_path_buf(),
        line,
        why: format!(
            "the line is longer than {max} bytes (the limit; raise it with --max-line-bytes); \
             is this the right file?"
        ),
    }
}

/// Reads one line into `buf` (cleared first), refusing lines over the line limit without
/// holding more than the limit in memory. `line` is the 1-based number of the line being read.
/// Returns the bytes read (0 at the end of the input).
pub fn read_line_limited<R: BufRead>(
    reader: &mut R,
    buf: &mut String,
    path: &Path,
    line: u64,
) -> Result<usize> {
    buf.clear();
    let max = max_line_bytes();
    let n = reader
        .by_ref()
        .take(max + 1)
        .read_line(buf)
        .map_err(|e| Error::io(path, e))?;
    if n as u64 > max && !buf.ends_with('\n') {
        return Err(line_too_long(path, line, max));
    }
    Ok(n)
}

/// An input over a reader limit: the line it is on and why.
#[derive(Debug)]
pub struct LimitExceeded {
    /// 1-based line.
    pub line: u64,
    /// What was exceeded.
    pub why: String,
}

impl std::fmt::Display for LimitExceeded {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "line {}: {}", self.line, self.why)
    }
}

impl std::error::Error for LimitExceeded {}

/// A reader that fails (with an [`std::io::Error`] wrapping [`LimitExceeded`]) as soon as a line
/// is longer than the line limit or has more `delimiter`s than the field limit allows, so a
/// parser downstream never buffers more than one bounded line.
#[derive(Debug)]
pub struct LimitedReader<R> {
    inner: R,
    delimiter: u8,
    line: u64,
    line_bytes: u64,
    fields: u64,
    max_line: u64,
    max_fields: u64,
}

impl<R: Read> LimitedReader<R> {
    /// Wraps `inner` with the process-wide limits.
    pub fn new(inner: R, delimiter: u8) -> Self {
        Self {
            inner,
            delimiter,
            line: 1,
            line_bytes: 0,
            fields: 1,
            max_line: max_line_bytes(),
            max_fields: max_fields(),
        }
    }
}

impl<R: Read> Read for LimitedReader<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        for &b in &buf[..n] {
            if b == b'\n' {
                self.line += 1;
                self.line_bytes = 0;
                self.fields = 1;
                continue;
            }
            self.line_bytes += 1;
            if b == self.delimiter {
                self.fields += 1;
            }
            let why = if self.line_bytes > self.max_line {
                format!(
                    "the line is longer than {} bytes (the limit; raise it with --max-line-bytes); \
                     is this the right file?",
                    self.max_line
                )
            } else if self.fields > self.max_fields {
                format!(
                    "more than {} fields (the limit; raise it with --max-fields)",
                    self.max_fields
                )
            } else {
                continue;
            };
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                LimitExceeded {
                    line: self.line,
                    why,
                },
            ));
        }
        Ok(n)
    }
}

/// The physical range of a column, by the unit suffix of its name: `(largest |value|, what)`.
pub fn column_range(name: &str) -> Option<(f64, &'static str)> {
    if name.ends_with("_nm_per_s") {
        Some((MAX_ABS_RATE_NM_PER_S, "removal rate"))
    } else if name.ends_with("_nm") {
        Some((MAX_ABS_HEIGHT_NM, "height"))
    } else if name.ends_with("_mm") {
        Some((MAX_ABS_COORDINATE_MM, "coordinate"))
    } else if name == "dwell_s" {
        Some((MAX_DWELL_S, "dwell time"))
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quotes_are_cut_to_80_characters() {
        let long = "é".repeat(500);
        let q = quote(&long);
        assert_eq!(q.chars().count(), QUOTE_CHARS + 3);
        assert_eq!(quote("short"), "short");
        let m = quote_message(&format!("a\n{long}\nb"));
        assert!(m.lines().all(|l| l.chars().count() <= QUOTE_CHARS + 3));
    }

    #[test]
    fn limited_reader_stops_long_lines_and_wide_rows_at_their_line() {
        let text = format!("a,b\n1,2\n{}\n", "9".repeat(3000));
        let mut r = LimitedReader {
            max_line: 1000,
            ..LimitedReader::new(text.as_bytes(), b',')
        };
        let mut out = Vec::new();
        let e = r.read_to_end(&mut out).unwrap_err();
        let inner = e
            .get_ref()
            .unwrap()
            .downcast_ref::<LimitExceeded>()
            .unwrap();
        assert_eq!(inner.line, 3);
        let text = format!("a,b\n{}\n", ",".repeat(20));
        let mut r = LimitedReader {
            max_fields: 10,
            ..LimitedReader::new(text.as_bytes(), b',')
        };
        let e = r.read_to_end(&mut out).unwrap_err().to_string();
        assert!(
            e.contains("line 2") && e.contains("more than 10 fields"),
            "{e}"
        );
        // Within the limits everything passes through unchanged.
        let mut out = Vec::new();
        LimitedReader::new(&b"x,y\n1,2\n"[..], b',')
            .read_to_end(&mut out)
            .unwrap();
        assert_eq!(out, b"x,y\n1,2\n");
    }

    #[cfg(unix)]
    #[test]
    fn non_regular_files_are_refused_without_reading() {
        let e = open_regular(Path::new("/dev/zero"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("a device"), "{e}");
        let dir = tempfile::tempdir().unwrap();
        let e = open_regular(dir.path()).unwrap_err().to_string();
        assert!(e.contains("a directory"), "{e}");
        let e = read_regular(Path::new("/dev/zero"), 10, "x")
            .unwrap_err()
            .to_string();
        assert!(e.contains("a device"), "{e}");
    }

    #[test]
    fn bounded_line_reads() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.txt");
        std::fs::write(&p, format!("ok\n{}\n", "x".repeat(2 << 20))).unwrap();
        let mut r = std::io::BufReader::new(open_regular(&p).unwrap());
        let mut buf = String::new();
        assert_eq!(read_line_limited(&mut r, &mut buf, &p, 1).unwrap(), 3);
        let e = read_line_limited(&mut r, &mut buf, &p, 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 2") && e.contains("longer than"), "{e}");
        let e = read_document(&p, "job file").unwrap_err().to_string();
        assert!(e.contains("line 2"), "{e}");
    }
}
