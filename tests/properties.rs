//! Property tests: random valid inputs round-trip through the readers; random invalid
//! inputs and random geometry give an error or an answer, never a panic.

use preston::io::job::Job;
use preston::io::readers::{read_map, read_tif};
use preston::io::table::{read_table_from, ColumnSpec};
use preston::solver::fit::{fit_xy_polynomial, ConicBase, FitSettings};
use preston::solver::surface::{Conic, Surface, XyPolynomial, XyTerm};
use preston::solver::tif::{GridTif, InfluenceFunction};
use proptest::prelude::*;
use std::path::Path;

const SPECS: [ColumnSpec; 3] = [
    ColumnSpec::required("x_mm"),
    ColumnSpec::required("y_mm"),
    ColumnSpec::required_skip("z_nm"),
];

/// Finite values within every column's physical range (|x|, |y| <= 1e5 mm, |z| <= 1e7 nm; see
/// `preston_io::limits`), bit patterns of every magnitude down to subnormals included.
fn finite() -> impl Strategy<Value = f64> {
    prop_oneof![
        -1e5..1e5f64,
        any::<f64>().prop_filter("finite, in range", |v| v.is_finite() && v.abs() <= 1e5),
        Just(1e5),
        Just(-1e5),
        Just(0.0),
        Just(-0.0),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    /// Any finite values, any column order, BOM or not, LF or CRLF: the reader returns exactly
    /// the written values (Rust's `{}` for f64 is the shortest round-trip form).
    #[test]
    fn map_values_round_trip(
        rows in prop::collection::vec((finite(), finite(), finite()), 1..40),
        order in Just([0usize, 1, 2]).prop_shuffle(),
        bom in any::<bool>(),
        crlf in any::<bool>(),
        extra in any::<bool>(),
    ) {
        let names = ["x_mm", "y_mm", "z_nm"];
        let eol = if crlf { "\r\n" } else { "\n" };
        let mut text = String::new();
        if bom { text.push('\u{feff}'); }
        let mut header: Vec<&str> = order.iter().map(|&k| names[k]).collect();
        if extra { header.push("note"); }
        text.push_str(&header.join(","));
        text.push_str(eol);
        for (x, y, z) in &rows {
            let v = [x, y, z];
            let mut cells: Vec<String> = order.iter().map(|&k| v[k].to_string()).collect();
            if extra { cells.push("a b".into()); }
            text.push_str(&cells.join(","));
            text.push_str(eol);
        }
        let t = read_table_from(text.as_bytes(), Path::new("p.csv"), &SPECS).unwrap();
        prop_assert_eq!(t.len(), rows.len());
        for (k, (x, y, z)) in rows.iter().enumerate() {
            prop_assert_eq!(t.column(0)[k].to_bits(), x.to_bits());
            prop_assert_eq!(t.column(1)[k].to_bits(), y.to_bits());
            prop_assert_eq!(t.column(2)[k].to_bits(), z.to_bits());
            prop_assert_eq!(t.lines[k], k as u64 + 2);
        }
    }

    /// A finite value beyond its column's physical range is an error naming its line and column.
    #[test]
    fn values_beyond_the_physical_range_are_named(
        n in 2usize..20,
        row in 0usize..20,
        col in 0usize..3,
        value in prop_oneof![1.0000001e5..1e308f64, -1e308..-1.0000001e5f64],
    ) {
        let row = row % n;
        // Heights may reach 1e7 nm: beyond 1e5 only the coordinates are out of range there.
        let value = if col == 2 { value.signum() * value.abs().max(1.0000001e7) } else { value };
        let names = ["x_mm", "y_mm", "z_nm"];
        let mut text = String::from("x_mm,y_mm,z_nm\n");
        for k in 0..n {
            let mut cells = [k.to_string(), (2 * k).to_string(), "1.5".to_string()];
            if k == row { cells[col] = value.to_string(); }
            text.push_str(&cells.join(","));
            text.push('\n');
        }
        let e = read_table_from(text.as_bytes(), Path::new("far.csv"), &SPECS)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        let line = format!("line {}", row + 2);
        let column = format!("`{}`", names[col]);
        prop_assert!(
            e.contains(&line) && e.contains(&column) && e.contains("physical range"),
            "{}",
            e
        );
    }

    /// Arbitrary bytes never panic the CSV reader.
    #[test]
    fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..400)) {
        let _ = read_table_from(&bytes[..], Path::new("junk.csv"), &SPECS);
    }

    /// A valid file with one cell replaced by garbage is rejected, naming that line and column.
    #[test]
    fn a_bad_cell_is_named(
        n in 2usize..20,
        row in 0usize..20,
        col in 0usize..3,
        junk in "[a-zA-Z#;]{1,6}|inf|-inf|1e999",
    ) {
        // An empty or NaN z_nm is a skipped row, not an error.
        prop_assume!(!(col == 2 && junk.eq_ignore_ascii_case("nan")));
        let row = row % n;
        let names = ["x_mm", "y_mm", "z_nm"];
        let mut text = String::from("x_mm,y_mm,z_nm\n");
        for k in 0..n {
            let mut cells = [k.to_string(), (2 * k).to_string(), "1.5".to_string()];
            if k == row { cells[col] = junk.clone(); }
            text.push_str(&cells.join(","));
            text.push('\n');
        }
        let e = read_table_from(text.as_bytes(), Path::new("bad.csv"), &SPECS)
            .err()
            .map(|e| e.to_string());
        let e = e.unwrap_or_default();
        let line = format!("line {}", row + 2);
        let column = format!("`{}`", names[col]);
        prop_assert!(e.contains("bad.csv") && e.contains(&line) && e.contains(&column), "{}", e);
    }

    /// Random job text never panics the job reader; an unknown key is always named.
    #[test]
    fn job_reader_never_panics(text in "\\PC{0,200}", key in "[a-z]{3,10}_[a-z]{2,6}") {
        let _ = Job::parse(&text, Path::new("job.toml"));
        let e = Job::parse(&format!("[machine]\n{key} = 1\n"), Path::new("job.toml"));
        let e = e.err().map(|e| e.to_string()).unwrap_or_default();
        prop_assert!(e.contains("job.toml") && e.contains(&key), "{}", e);
    }

    /// Random XY polynomials evaluated anywhere give a finite answer or an error, never a panic
    /// or a NaN; inside the conic's domain they always answer, with a unit normal.
    #[test]
    fn surfaces_answer_or_refuse(
        c in -0.05..0.05f64,
        k in -3.0..3.0f64,
        coefs in prop::collection::vec(-1.0..1.0f64, 9),
        x in -200.0..200.0f64,
        y in -200.0..200.0f64,
    ) {
        let terms = [(1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3)]
            .iter()
            .zip(&coefs)
            .map(|(&(m, n), &coef_mm)| XyTerm { m, n, coef_mm })
            .collect();
        let s = Surface::XyPolynomial(XyPolynomial {
            curvature_per_mm: c,
            conic: k,
            norm_radius_mm: 50.0,
            terms,
        });
        let inside = 1.0 - (1.0 + k) * c * c * (x * x + y * y) > 1e-9;
        match s.derivs(x, y) {
            Ok(d) => {
                prop_assert!(d.z.is_finite());
                let n = d.normal();
                let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                prop_assert!((len - 1.0).abs() < 1e-12);
            }
            Err(e) => prop_assert!(!inside, "refused inside the domain: {}", e),
        }
        let disc = 1.0 - (1.0 + k) * c * c * (x * x + y * y);
        prop_assume!(disc.abs() > 1e-12);
        let conic = Surface::Conic(Conic { curvature_per_mm: c, conic: k });
        prop_assert_eq!(conic.sag_mm(x, y).is_ok(), disc > 0.0);
    }

    /// Fitting random (possibly degenerate) point sets gives an error or a finite fit.
    #[test]
    fn fitting_answers_or_refuses(
        pts in prop::collection::vec((-50.0..50.0f64, -50.0..50.0f64, -1.0..1.0f64), 0..30),
        collinear in any::<bool>(),
        order in 0u32..4,
    ) {
        let x: Vec<f64> = pts.iter().map(|p| p.0).collect();
        let y: Vec<f64> = if collinear { x.clone() } else { pts.iter().map(|p| p.1).collect() };
        let z: Vec<f64> = pts.iter().map(|p| p.2).collect();
        let settings = FitSettings {
            order,
            base: ConicBase::Fixed { curvature_per_mm: 0.0, conic: 0.0 },
            ..FitSettings::default()
        };
        if let Ok(f) = fit_xy_polynomial(&x, &y, &z, &settings) {
            prop_assert!(f.rms_nm.is_finite() && f.condition_number.is_finite());
            prop_assert!(!(collinear && order >= 1), "collinear points determined order {}", order);
        }
    }

    /// Random grids: a TIF is built (finite, non-negative, not all zero, regular) or refused.
    #[test]
    fn tif_grids_answer_or_refuse(
        nx in 1usize..6,
        ny in 1usize..6,
        rates in prop::collection::vec(prop_oneof![-1.0..10.0f64, Just(0.0), Just(f64::NAN)], 36),
        jitter in prop_oneof![Just(0.0), 0.01..0.5f64],
    ) {
        let mut x = Vec::new();
        let mut y = Vec::new();
        let mut r = Vec::new();
        for iy in 0..ny {
            for ix in 0..nx {
                x.push(ix as f64 + if ix == 1 { jitter } else { 0.0 });
                y.push(iy as f64);
                r.push(rates[iy * 6 + ix]);
            }
        }
        // Two columns are equally spaced whatever the jitter; three or more are not.
        let valid = nx >= 2 && ny >= 2 && (nx == 2 || jitter == 0.0)
            && r.iter().all(|v| v.is_finite() && *v >= 0.0)
            && r.iter().any(|v| *v > 0.0);
        match GridTif::from_samples(&x, &y, &r) {
            Ok(t) => {
                prop_assert!(valid, "accepted an invalid grid");
                prop_assert!(t.rate_nm_per_s(0.3, 0.3).is_finite());
            }
            Err(_) => prop_assert!(!valid),
        }
    }
}

/// The readers reject files that are not there, naming them (no panic on I/O errors).
#[test]
fn missing_files_are_named() {
    let e = read_map(Path::new("/nonexistent/map.csv"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("/nonexistent/map.csv"), "{e}");
    let e = read_tif(Path::new("/nonexistent/tif.csv"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("/nonexistent/tif.csv"), "{e}");
}
