//! Helpers shared by the unit tests.

/// `f()` run on a rayon pool of `threads` threads (the determinism tests compare the bits of
/// one result across thread counts).
pub(crate) fn on_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a rayon pool for a test")
        .install(f)
}
