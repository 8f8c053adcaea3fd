//! Inputs that cannot be what the user meant, refused with exit 2, a message naming the file and
//! what is wrong with it, and nothing written: a map file whose header states sizes it cannot
//! hold (refused before a buffer of that size is allocated, so an address-space cap cannot turn
//! it into an abort), and a TIF whose footprint fits between the map's points. And a solve's
//! console summary, which says what its figures are of, so that a correct plan does not read
//! as a failed one.

mod common;

use common::{expect_failure, preston_cmd, s, write};
use std::path::Path;
use std::process::Output;

/// Address-space cap under which the refused commands run, KiB (2 GiB): a buffer of the size a
/// hostile header states (4 GiB) cannot be had under it, so an allocation aborts the process
/// (exit 134) instead of being refused.
const ADDRESS_SPACE_KIB: u64 = 2 << 20;

/// Runs `preston ARGS` with the address space capped at [`ADDRESS_SPACE_KIB`] on Linux.
fn capped(args: &[&str]) -> Output {
    let mut c = if cfg!(target_os = "linux") {
        let mut c = std::process::Command::new("sh");
        c.arg("-c")
            .arg(format!(
                "ulimit -v {ADDRESS_SPACE_KIB} && exec \"$0\" \"$@\""
            ))
            .arg(common::exe());
        c
    } else {
        preston_cmd()
    };
    c.args(args).output().unwrap()
}

/// Asserts exit 2, every needle in stderr, no panic, and nothing under `out`.
fn refused(o: &Output, out: &Path, needles: &[&str]) {
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "exit {:?}: {err}", o.status);
    assert!(!err.contains("panicked"), "{err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks `{n}`: {err}");
    }
    assert!(
        !out.exists() || std::fs::read_dir(out).unwrap().next().is_none(),
        "output written despite the error"
    );
}

/// The Gaussian TIF and raster of a solve whose map is the file under test.
const SOLVE_TAIL: [&str; 10] = [
    "--gaussian-sigma-mm",
    "1",
    "--gaussian-peak-nm-per-s",
    "10",
    "--gaussian-truncation-mm",
    "3",
    "--raster-pitch-mm",
    "1",
    "--v-max",
    "3000",
];

/// A 20-byte `.npy` of format 2 whose 4-byte header length states 4 GiB - 1: refused from the
/// preamble (exit 2, the file and the stated length named) under a 2 GiB address cap and a
/// 1 GB budget, where allocating the header it states aborts the process.
#[test]
fn an_npy_header_length_past_the_file_is_refused_before_allocating() {
    let d = tempfile::tempdir().unwrap();
    let map = d.path().join("hostile.npy");
    let mut b = b"\x93NUMPY\x02\x00".to_vec();
    b.extend_from_slice(&u32::MAX.to_le_bytes());
    b.extend_from_slice(b"{'descr'");
    assert_eq!(b.len(), 20);
    std::fs::write(&map, &b).unwrap();
    let out = d.path().join("result");
    let mut args = vec![
        "--max-memory-gb",
        "1",
        "solve",
        "--map",
        s(&map),
        "--pitch-mm",
        "1",
    ];
    args.extend(SOLVE_TAIL);
    args.extend(["--out", s(&out)]);
    let o = capped(&args);
    refused(
        &o,
        &out,
        &[
            "hostile.npy",
            "NPY header",
            &u32::MAX.to_string(),
            "20 bytes",
        ],
    );
}

/// A `.npy` whose well-formed header declares a 30000 x 30000 `f8` grid (7.2 GB of values) with
/// no data behind it: refused as truncated, naming the file and the bytes the shape needs,
/// before the values are read.
#[test]
fn an_npy_shape_the_file_cannot_hold_is_refused_before_reading() {
    let d = tempfile::tempdir().unwrap();
    let map = d.path().join("shape.npy");
    let dict = "{'descr': '<f8', 'fortran_order': False, 'shape': (30000, 30000), }";
    let mut header = dict.as_bytes().to_vec();
    while !(10 + header.len() + 1).is_multiple_of(64) {
        header.push(b' ');
    }
    header.push(b'\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(header.len() as u16).to_le_bytes());
    b.extend_from_slice(&header);
    std::fs::write(&map, &b).unwrap();
    let out = d.path().join("result");
    let mut args = vec![
        "--max-memory-gb",
        "1",
        "solve",
        "--map",
        s(&map),
        "--pitch-mm",
        "1",
    ];
    args.extend(SOLVE_TAIL);
    args.extend(["--out", s(&out)]);
    let o = capped(&args);
    let needed = (30000u64 * 30000 * 8).to_string();
    refused(&o, &out, &["shape.npy", "NPY data", "truncated", &needed]);
}

/// A smooth 21 x 21 map at 1 mm pitch.
fn map_1mm() -> String {
    let mut t = String::from("x_mm,y_mm,z_nm\n");
    for iy in 0..21 {
        for ix in 0..21 {
            let (x, y) = (ix as f64, iy as f64);
            let z = 40.0 + 25.0 * (0.31 * x).sin() * (0.23 * y).cos() + 0.8 * y;
            t.push_str(&format!("{x},{y},{z}\n"));
        }
    }
    t
}

/// A 10 mm TIF grid (Gaussian of sigma 2 mm, 0.5 mm spacing) with its coordinates written in
/// metres under the `x_mm, y_mm` header: `scale` 1e-3 for metres, 1 for mm.
fn tif_grid(scale: f64) -> String {
    let mut t = String::from("x_mm,y_mm,rate_nm_per_s\n");
    for iy in -10..=10 {
        for ix in -10..=10 {
            let (x, y) = (ix as f64 * 0.5, iy as f64 * 0.5);
            let r = 10.0 * (-(x * x + y * y) / (2.0 * 2.0f64.powi(2))).exp();
            t.push_str(&format!("{},{},{r}\n", x * scale, y * scale));
        }
    }
    t
}

/// The 10 mm TIF in metres under an `x_mm` header, on a 1 mm map with the raster on the map's
/// lattice: every dwell point sits on a map point, so each reaches one and the old check (no
/// dwell point reaches the map) let it through to a solve that exits 0. Its support radius
/// (5 um) is below half the map's 1 mm spacing: exit 2, suggesting the unit, nothing written.
/// The same TIF in mm solves.
#[test]
fn a_tif_in_metres_under_an_mm_header_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_1mm());
    let tif_m = write(d.path(), "tif_metres.csv", &tif_grid(1e-3));
    let args = |tif: &Path| -> Vec<String> {
        [
            "--map",
            s(&map),
            "--tif",
            s(tif),
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "3000",
        ]
        .map(String::from)
        .to_vec()
    };
    let a = args(&tif_m);
    let refs: Vec<&str> = a.iter().map(String::as_str).collect();
    expect_failure(&refs, &["narrower", "spacing", "in mm", "metres"]);
    let tif_mm = write(d.path(), "tif_mm.csv", &tif_grid(1.0));
    let out = d.path().join("mm");
    let o = preston_cmd()
        .arg("solve")
        .args(args(&tif_mm))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(!err.contains("narrower"), "{err}");
}

/// Jenkins' lookup3 `hashlittle` (initial value 0): the checksum HDF5 stores after each
/// version-2 object header, recomputed after a test patches one.
fn lookup3(data: &[u8]) -> u32 {
    fn mix(a: &mut u32, b: &mut u32, c: &mut u32) {
        for (x, y, z, k) in [(0, 2, 1, 4), (1, 0, 2, 6), (2, 1, 0, 8)]
            .into_iter()
            .chain([(0, 2, 1, 16), (1, 0, 2, 19), (2, 1, 0, 4)])
        {
            let mut v = [*a, *b, *c];
            v[x] = v[x].wrapping_sub(v[y]);
            v[x] ^= v[y].rotate_left(k);
            v[y] = v[y].wrapping_add(v[z]);
            [*a, *b, *c] = v;
        }
    }
    fn final_mix(a: &mut u32, b: &mut u32, c: &mut u32) {
        for (x, y, k) in [
            (2, 1, 14),
            (0, 2, 11),
            (1, 0, 25),
            (2, 1, 16),
            (0, 2, 4),
            (1, 0, 14),
            (2, 1, 24),
        ] {
            let mut v = [*a, *b, *c];
            v[x] ^= v[y];
            v[x] = v[x].wrapping_sub(v[y].rotate_left(k));
            [*a, *b, *c] = v;
        }
    }
    let word = |d: &[u8]| {
        d.iter()
            .enumerate()
            .fold(0u32, |w, (i, &b)| w | (u32::from(b) << (8 * i)))
    };
    let init = 0xdead_beefu32.wrapping_add(data.len() as u32);
    let (mut a, mut b, mut c) = (init, init, init);
    let mut rest = data;
    while rest.len() > 12 {
        a = a.wrapping_add(word(&rest[0..4]));
        b = b.wrapping_add(word(&rest[4..8]));
        c = c.wrapping_add(word(&rest[8..12]));
        mix(&mut a, &mut b, &mut c);
        rest = &rest[12..];
    }
    if rest.is_empty() {
        return c;
    }
    let w: Vec<u32> = rest.chunks(4).map(word).collect();
    a = a.wrapping_add(w[0]);
    b = b.wrapping_add(w.get(1).copied().unwrap_or(0));
    c = c.wrapping_add(w.get(2).copied().unwrap_or(0));
    final_mix(&mut a, &mut b, &mut c);
    c
}

/// The published self-test value of lookup3.c, so that a patched header's checksum is HDF5's.
#[test]
fn lookup3_matches_its_published_value() {
    assert_eq!(lookup3(b"Four score and seven years ago"), 0x1777_0551);
    assert_eq!(lookup3(b""), 0xdead_beef);
}

/// A `.datx` of a 37 x 41 surface whose dataset header is patched to declare 30000 x 30000
/// pixels (its checksum recomputed): a file of a few kilobytes whose chunked dataset, read,
/// would fill 7.2 GB. Refused from the declared shape against a 1 GB budget, before reading:
/// exit 2 naming the file, the dataset and the grid's size.
#[test]
fn a_datx_declaring_a_grid_over_the_budget_is_refused_before_reading() {
    let d = tempfile::tempdir().unwrap();
    let map = d.path().join("declared.datx");
    let (nx, ny) = (41usize, 37usize);
    let z: Vec<f64> = (0..nx * ny).map(|k| (k as f64 * 0.1).sin()).collect();
    preston_io::metrology::write_zygo_datx(
        &map,
        nx,
        ny,
        0.5,
        &z,
        preston_io::metrology::DatxUnit::NanoMeters,
    )
    .unwrap();
    let mut b = std::fs::read(&map).unwrap();
    let mut dims = (ny as u64).to_le_bytes().to_vec();
    dims.extend_from_slice(&(nx as u64).to_le_bytes());
    let at = b
        .windows(16)
        .position(|w| w == dims.as_slice())
        .expect("the dataspace's dimensions");
    let ohdr = b[..at]
        .windows(4)
        .rposition(|w| w == b"OHDR")
        .expect("the dataset's object header");
    // Version-2 object header prefix: signature, version, flags, optional times (16 bytes) and
    // attribute phase values (4), then chunk 0's size in 1, 2, 4 or 8 bytes.
    let flags = b[ohdr + 5];
    let mut p = ohdr + 6;
    if flags & 0x20 != 0 {
        p += 16;
    }
    if flags & 0x10 != 0 {
        p += 4;
    }
    let width = 1usize << (flags & 0x03);
    let size = b[p..p + width]
        .iter()
        .rev()
        .fold(0usize, |s, &v| (s << 8) | usize::from(v));
    let end = p + width + size;
    assert!(at > ohdr && at + 16 <= end, "dimensions outside the header");
    let mut big = 30000u64.to_le_bytes().to_vec();
    big.extend_from_slice(&30000u64.to_le_bytes());
    // The dimensions, and the maximum dimensions where the dataspace states them.
    let mut k = ohdr;
    while let Some(off) = b[k..end].windows(16).position(|w| w == dims.as_slice()) {
        b[k + off..k + off + 16].copy_from_slice(&big);
        k += off + 16;
    }
    let sum = lookup3(&b[ohdr..end]);
    b[end..end + 4].copy_from_slice(&sum.to_le_bytes());
    std::fs::write(&map, &b).unwrap();
    assert!(b.len() < 64 * 1024, "{} bytes", b.len());
    let out = d.path().join("result");
    let mut args = vec!["--max-memory-gb", "1", "solve", "--map", s(&map)];
    args.extend(SOLVE_TAIL);
    args.extend(["--out", s(&out)]);
    let o = capped(&args);
    refused(
        &o,
        &out,
        &[
            "declared.datx",
            "/Data/Surface/0",
            "30000 x 30000",
            "28.800 GB",
        ],
    );
}

/// A solve corrected against its program executed at an acceleration limit (correction
/// passes), its operator the FFT one under the swept model: the summary names which solve its
/// iteration count is of, explains the programmed feeds' acceleration above the limit as what
/// the look-ahead holds, prints the exact swept columns as a note (not a warning), and
/// `report.json` gives the largest stretch departure under a key naming its unit.
#[test]
fn the_console_summary_names_its_stage_units_and_notes() {
    let d = tempfile::tempdir().unwrap();
    let map = write(d.path(), "map.csv", &map_1mm());
    let out = d.path().join("result");
    let o = preston_cmd()
        .args([
            "solve",
            "--map",
            s(&map),
            "--gaussian-sigma-mm",
            "1.5",
            "--gaussian-peak-nm-per-s",
            "10",
            "--gaussian-truncation-mm",
            "4.5",
            "--raster-pitch-mm",
            "1",
            "--v-max",
            "3000",
            "--a-max-mm-per-s2",
            "50",
            "--accel-method",
            "correction-passes",
            "--operator",
            "fft",
            "--out",
            s(&out),
        ])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "{err}");
    let r = common::report(&out);
    let executed = &r["executed"];
    assert!(
        executed["max_stretch_error_rel"].as_f64().is_some(),
        "{executed}"
    );
    assert!(executed.get("max_stretch_error").is_none(), "{executed}");
    assert!(err.contains("note: influence swept:"), "{err}");
    assert!(!err.contains("warning: influence swept"), "{err}");
    assert!(
        !r["warnings"].to_string().contains("influence swept"),
        "{r}"
    );
    assert!(r["notes"].to_string().contains("influence swept"), "{r}");
    let passes = executed["correction_passes"].as_u64().unwrap();
    let iterations = r["iterations"].as_u64().unwrap();
    eprintln!("passes {passes}, iterations {iterations}\n{err}");
    assert!(
        passes > 0,
        "the case is meant to keep a correction pass: {err}"
    );
    assert!(
        err.contains(&format!(
            "{iterations} iterations in correction pass {passes}, the last kept"
        )),
        "{err}"
    );
    let a_max = r["a_max_mm_per_s2"].as_f64().unwrap();
    let programmed = r["max_accel_mm_per_s2"].as_f64().unwrap();
    assert!(programmed > a_max, "{programmed} vs {a_max}");
    assert!(
        err.contains("the programmed feeds step at up to")
            && err.contains("look-ahead holds to the"),
        "{err}"
    );
}
