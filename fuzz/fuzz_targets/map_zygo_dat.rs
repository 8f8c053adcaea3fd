//! Arbitrary bytes as a map file read as `MapFormat::ZygoDat` (see `common/map.rs`).
#![no_main]

#[path = "common/map.rs"]
mod map;

use libfuzzer_sys::fuzz_target;
use preston_io::metrology::MapFormat;
use std::path::PathBuf;
use std::sync::OnceLock;

static PATH: OnceLock<PathBuf> = OnceLock::new();

fuzz_target!(|data: &[u8]| {
    map::check(data, MapFormat::ZygoDat, "dat", &PATH);
});
