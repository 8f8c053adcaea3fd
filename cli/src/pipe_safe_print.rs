//! Printing that treats a closed stdout or stderr as the end of printing.
//!
//! `println!` and `eprintln!` panic when the stream's reader has gone (`preston solve ... | head
//! -1` closes the pipe after one line; the process then exits 101 after its outputs are written).
//! Every message of the binary goes through [`outln!`](crate::outln) and
//! [`errln!`](crate::errln) instead: a write that fails with a broken pipe marks the stream
//! closed, and later writes to it are dropped silently. Other write errors are dropped too: a
//! message that cannot be shown must not turn a completed run into a failure.

use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};

static STDOUT_CLOSED: AtomicBool = AtomicBool::new(false);
static STDERR_CLOSED: AtomicBool = AtomicBool::new(false);

/// Which stream a message goes to.
#[derive(Debug, Clone, Copy)]
pub enum Stream {
    /// Standard output (results a script reads).
    Out,
    /// Standard error (progress, warnings, errors).
    Err,
}

/// Writes `args` to `stream` unless it is known to be closed; a broken pipe marks it closed.
pub fn write(stream: Stream, args: std::fmt::Arguments<'_>) {
    let closed = match stream {
        Stream::Out => &STDOUT_CLOSED,
        Stream::Err => &STDERR_CLOSED,
    };
    if closed.load(Ordering::Relaxed) {
        return;
    }
    let result = match stream {
        Stream::Out => {
            let mut s = std::io::stdout().lock();
            s.write_fmt(args).and_then(|()| s.flush())
        }
        Stream::Err => std::io::stderr().lock().write_fmt(args),
    };
    if let Err(e) = result {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            closed.store(true, Ordering::Relaxed);
        }
    }
}

/// `println!` that ends printing on a closed pipe instead of panicking.
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::pipe_safe_print::write($crate::pipe_safe_print::Stream::Out, format_args!("{}\n", format_args!($($arg)*)))
    };
}

/// `print!` that ends printing on a closed pipe instead of panicking.
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::pipe_safe_print::write($crate::pipe_safe_print::Stream::Out, format_args!($($arg)*))
    };
}

/// `eprintln!` that ends printing on a closed pipe instead of panicking.
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => {
        $crate::pipe_safe_print::write($crate::pipe_safe_print::Stream::Err, format_args!("{}\n", format_args!($($arg)*)))
    };
}

/// `eprint!` that ends printing on a closed pipe instead of panicking.
#[macro_export]
macro_rules! err {
    ($($arg:tt)*) => {
        $crate::pipe_safe_print::write($crate::pipe_safe_print::Stream::Err, format_args!($($arg)*))
    };
}
