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

/// `n` deterministic pseudo-random points in [0, 20) x [0, 10) mm (splitmix64 from `seed`).
pub(crate) fn scattered(n: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let mut s = seed;
    let mut next = || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n).map(|_| (20.0 * next(), 10.0 * next())).unzip()
}
