//! Arbitrary bytes into the streaming CSV reader (`preston_io::table::read_table_from`) with the
//! height-map columns. Errors are fine; a panic is a bug. When the reader accepts the input, the
//! table must satisfy its documented invariants: finite values, equal column lengths (one value
//! per kept row) and strictly increasing 1-based line numbers.
#![no_main]

use libfuzzer_sys::fuzz_target;
use preston_io::table::{read_table_from, ColumnSpec};
use std::path::Path;

const SPECS: [ColumnSpec; 3] = [
    ColumnSpec::required("x_mm"),
    ColumnSpec::required("y_mm"),
    ColumnSpec::required_skip("z_nm"),
];

fuzz_target!(|data: &[u8]| {
    let Ok(t) = read_table_from(data, Path::new("fuzz.csv"), &SPECS) else {
        return;
    };
    assert_eq!(
        t.columns.len(),
        SPECS.len(),
        "one entry per requested column"
    );
    for (k, col) in t.columns.iter().enumerate() {
        let col = col.as_ref().expect("required columns are always present");
        assert_eq!(col.len(), t.lines.len(), "column {k} length vs kept rows");
        assert!(
            col.iter().all(|v| v.is_finite()),
            "column {k} has a non-finite value: {col:?}"
        );
    }
    assert_eq!(t.len(), t.lines.len());
    assert!(
        t.lines.iter().all(|&l| l >= 2),
        "data rows start at line 2: {:?}",
        t.lines
    );
    assert!(
        t.lines.windows(2).all(|w| w[0] < w[1]),
        "line numbers not strictly increasing: {:?}",
        t.lines
    );
});
