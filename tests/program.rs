//! G-code program fidelity: the program as written, read back and timed block by block,
//! delivers every planned dwell, in every dialect and feed mode.

use preston::solver::machine::gcode::dialect::{Dialect, FeedMode};
use preston::solver::machine::gcode::motion::{check_stretches, contact_xy, execute, Kinematics};
use preston::solver::machine::gcode::program::{BlockKind, Program};
use preston::solver::machine::gcode::write::{write_program, FEED_ROUNDING};
use preston::solver::machine::nc::{NcProgram, NcSettings, ToolAxis};
use preston::solver::machine::profile::{Coolant, WorkOffset};
use preston::solver::machine::{Flat, PartGeometry};
use preston::solver::path::DwellPath;
use preston::solver::surface::{Conic, Surface};
use proptest::prelude::*;

/// A stretch time may move by the relative rounding of F only (coordinates are timed as written).
const STRETCH_TOL: f64 = 1.5 * FEED_ROUNDING;

const MODES: [FeedMode; 2] = [FeedMode::PerMinute, FeedMode::InverseTime];

fn settings(dialect: Dialect, feed_mode: FeedMode) -> NcSettings {
    NcSettings {
        dialect,
        feed_mode,
        min_block_time_ms: 0.0,
        ..NcSettings::default()
    }
}

/// Writes, reads back and checks every stretch against the plan.
fn assert_delivers(path: &DwellPath, dwell_s: &[f64], geometry: &dyn PartGeometry, s: &NcSettings) {
    let nc = NcProgram::plan(path, dwell_s, geometry, s).unwrap();
    let w = write_program(&nc, &[]).unwrap();
    let p = Program::parse(&w.text, s.dialect).unwrap();
    assert_eq!(p.stretches.len(), dwell_s.len());
    let times = p.programmed_stretch_times_s();
    for (k, (m, t)) in p.stretches.iter().zip(&times).enumerate() {
        assert_eq!(m.point, k);
        // The marker's dwell has 7 significant digits (at most 9 decimals).
        let written = (m.planned_dwell_s - dwell_s[k]).abs();
        assert!(
            written <= 5e-7 * dwell_s[k] + 5e-10,
            "{} vs {}",
            m.planned_dwell_s,
            dwell_s[k]
        );
        assert!(
            (t - dwell_s[k]).abs() <= STRETCH_TOL * dwell_s[k],
            "{:?} {:?}: stretch {k}: {t} s for {} s",
            s.dialect,
            s.feed_mode,
            dwell_s[k]
        );
    }
    let planned: f64 = dwell_s.iter().sum();
    let programmed: f64 = times.iter().sum();
    assert!((programmed - planned).abs() <= STRETCH_TOL * planned);
    // Machining time (all feed blocks) is never below the dwell.
    assert!(p.programmed_time_s() >= planned * (1.0 - STRETCH_TOL));
    // The executed model at the programmed feeds agrees with the block sums.
    let e = execute(&p, Kinematics::ProgrammedFeed).unwrap();
    let c = check_stretches(&p, &e);
    assert!(c.max_relative_error <= STRETCH_TOL, "{c:?}");
}

fn serpentine(cols: usize, rows: usize, pitch: f64) -> DwellPath {
    let (mut x, mut y) = (Vec::new(), Vec::new());
    for r in 0..rows {
        for c in 0..cols {
            let c = if r % 2 == 0 { c } else { cols - 1 - c };
            x.push(c as f64 * pitch);
            y.push(r as f64 * pitch);
        }
    }
    DwellPath::new(x, y).unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Random walks with random feeds over six decades (0.01 to 10^4 mm/min): every stretch of
    /// the program takes its dwell, in every dialect and feed mode.
    #[test]
    fn every_stretch_takes_its_dwell(
        steps in proptest::collection::vec((0.05f64..3.0, -3.2f64..3.2), 2..40),
        log_feeds in proptest::collection::vec(-2.0f64..4.0, 41),
    ) {
        let (mut x, mut y) = (vec![0.0], vec![0.0]);
        for (len, angle) in &steps {
            let (px, py) = (x[x.len() - 1], y[y.len() - 1]);
            x.push(px + len * angle.cos());
            y.push(py + len * angle.sin());
        }
        let path = DwellPath::new(x, y).unwrap();
        let ds = path.ds_mm();
        let dwell: Vec<f64> = ds
            .iter()
            .zip(&log_feeds)
            .map(|(d, lf)| 60.0 * d / 10f64.powf(*lf))
            .collect();
        for d in Dialect::ALL {
            for m in MODES {
                assert_delivers(&path, &dwell, &Flat, &settings(d, m));
            }
        }
    }
}

#[test]
fn round_trip_in_every_dialect_and_feed_mode() {
    let path = serpentine(5, 3, 1.5);
    let dwell: Vec<f64> = (0..15)
        .map(|j| 0.05 + 0.37 * ((j * 7) % 11) as f64)
        .collect();
    let sphere = Surface::Conic(Conic {
        curvature_per_mm: 1.0 / 80.0,
        conic: 0.0,
    });
    for d in Dialect::ALL {
        for m in MODES {
            let s = NcSettings {
                tool_radius_mm: 4.0,
                tool_axis: ToolAxis::Normal,
                spindle_rpm: Some(600.0),
                coolant: Coolant::Flood,
                ..settings(d, m)
            };
            let nc = NcProgram::plan(&path, &dwell, &sphere, &s).unwrap();
            let w = write_program(&nc, &["JOB (TEST)".into()]).unwrap();
            assert_eq!(Program::detect_dialect(&w.text), Some(d));
            let p = Program::parse(&w.text, d).unwrap();
            // Every feed block of a stretch ends where the writer put it: at the point or the
            // next boundary, to the 4 written decimals.
            for (j, pt) in nc.points.iter().enumerate() {
                let b = &p.blocks[p.stretch_blocks(j)];
                assert_eq!(b.len(), 2, "{d:?} {m:?} stretch {j}");
                for k in 0..3 {
                    assert!((b[0].end_mm[k] - pt.tool_mm[k]).abs() <= 0.51e-4);
                    assert!((b[1].end_mm[k] - nc.boundaries[j + 1].tool_mm[k]).abs() <= 0.51e-4);
                }
                assert!((b[0].rotary_deg[1] - pt.b_deg.unwrap()).abs() <= 0.51e-4);
            }
            // Approach: rapids, then a plunge at the plunge feed; retract after END DWELL.
            assert_eq!(p.blocks[0].kind, BlockKind::Rapid);
            assert_eq!(p.blocks[2].kind, BlockKind::Linear);
            assert!(!p.blocks[2].contact && p.blocks[3].contact);
            assert_eq!(p.blocks.last().unwrap().kind, BlockKind::Rapid);
            let plunge = p.blocks[2].length_mm() / p.blocks[2].programmed_time_s * 60.0;
            assert!((plunge - 300.0).abs() < 1e-3 * 300.0, "{plunge}");
            // The header's machining time is the sum of the programmed block times.
            let header = w
                .text
                .lines()
                .find(|l| l.contains("MACHINING TIME"))
                .unwrap();
            let stated: f64 = header
                .split_whitespace()
                .nth(if d == Dialect::Sinumerik { 3 } else { 2 })
                .unwrap()
                .parse()
                .unwrap();
            assert!((stated - p.programmed_time_s()).abs() <= 1e-3 + 1e-4 * stated);
            if d == Dialect::Sinumerik {
                assert!(!w.text.contains('('), "parenthesis in a Sinumerik program");
            }
            assert_eq!(w.text.contains(" G93"), m == FeedMode::InverseTime);
            assert!(w.text.contains(" M8") && w.text.contains("M5"));
            assert_delivers(&path, &dwell, &sphere, &s);
        }
    }
}

#[test]
fn hand_computed_three_point_program() {
    // Points (0,0), (2,0), (2,1) with dwell 1, 0.5, 2 s on a flat part, no tool radius.
    // Stretches: [-1,0]->(0,0)->(1,0): 2 mm in 1 s: F120; (1,0)->(2,0)->(2,0.5): 1.5 mm in 0.5 s:
    // F180; (2,0.5)->(2,1)->(2,1.5): 1 mm in 2 s: F30.
    let path = DwellPath::new(vec![0.0, 2.0, 2.0], vec![0.0, 0.0, 1.0]).unwrap();
    let nc = NcProgram::plan(&path, &[1.0, 0.5, 2.0], &Flat, &NcSettings::default()).unwrap();
    let text = write_program(&nc, &[]).unwrap().text;
    let want = [
        "N1 G17 G21 G40 G80 G90 G94",
        "N2 G17 G21 G54 G90 G94",
        "N3 G00 Z5.0000",
        "N4 G00 X-1.0000 Y0.0000",
        "N5 G01 Z0.0000 F300.000",
        "(DWELL 0 1.000000 S AT 0.0000 0.0000)",
        "N6 G01 X0.0000 Y0.0000 Z0.0000 F120.000",
        "N7 G01 X1.0000 Y0.0000 Z0.0000 F120.000",
        "(DWELL 1 0.5000000 S AT 2.0000 0.0000)",
        "N8 G01 X2.0000 Y0.0000 Z0.0000 F180.000",
        "N9 G01 X2.0000 Y0.5000 Z0.0000 F180.000",
        "(DWELL 2 2.000000 S AT 2.0000 1.0000)",
        "N10 G01 X2.0000 Y1.0000 Z0.0000 F30.000",
        "N11 G01 X2.0000 Y1.5000 Z0.0000 F30.000",
        "(END DWELL)",
        "N12 G00 Z5.0000",
        "N13 M30",
        "%",
    ];
    let lines: Vec<&str> = text.lines().collect();
    let at = lines.iter().position(|l| l.starts_with("N1 ")).unwrap();
    assert_eq!(&lines[at..], &want[..], "{text}");
    // Read back: 1 + 0.5 + 2 s in the stretches, the plunge 5 mm at 300 mm/min = 1 s.
    let p = Program::parse(&text, Dialect::Iso).unwrap();
    let t = p.programmed_stretch_times_s();
    assert_eq!(t.len(), 3);
    for (got, want) in t.iter().zip([1.0, 0.5, 2.0]) {
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
    }
    assert!((p.programmed_time_s() - 4.5).abs() < 1e-12);
}

#[test]
fn reader_handles_dialect_words_and_refuses_what_it_cannot_time() {
    // Sinumerik: `;` comments, G4 F seconds, G71; Fanuc: G04 X seconds; inch units.
    let sin = "G17 G71 G90 G94\nG0 X0 Y0 Z1\nG1 Z0 F60 ; plunge 1 mm in 1 s\nG4 F2.5\nG1 X3 Y4 F300\nM30\n";
    let p = Program::parse(sin, Dialect::Sinumerik).unwrap();
    let t: Vec<f64> = p.blocks.iter().map(|b| b.programmed_time_s).collect();
    assert_eq!(t, vec![0.0, 1.0, 2.5, 1.0]);
    let fanuc =
        "%\nO1000\nG21 G90 G94\nG00 X0 Y0 Z0\nG04 X1.5\nG04 P250\nG20\nG01 X1. F10.\nM30\n%\n";
    let p = Program::parse(fanuc, Dialect::Fanuc).unwrap();
    let t: Vec<f64> = p.blocks.iter().map(|b| b.programmed_time_s).collect();
    assert!((t[1] - 1.5).abs() < 1e-12 && (t[2] - 0.25).abs() < 1e-12);
    // 1 inch at 10 inch/min: 6 s, and the end point in mm.
    assert!((t[3] - 6.0).abs() < 1e-12 && (p.blocks[3].end_mm[0] - 25.4).abs() < 1e-12);
    // Fanuc counts the rotary axis in the path length; ISO does not.
    let rot = "G0 X0 Y0 Z0 B0\nG1 X3 Y4 B12 F60\n";
    let iso = Program::parse(rot, Dialect::Iso).unwrap();
    let fan = Program::parse(rot, Dialect::Fanuc).unwrap();
    assert!((iso.blocks[1].programmed_time_s - 5.0).abs() < 1e-12);
    assert!((fan.blocks[1].programmed_time_s - 13.0).abs() < 1e-12);
    // Inverse time: 60 / F seconds, F required in every block.
    let g93 = "G0 X0 Y0 Z0\nG93 G1 X1 F120\nG1 X2 F30\n";
    let p = Program::parse(g93, Dialect::Linuxcnc).unwrap();
    assert_eq!(p.blocks[1].programmed_time_s, 0.5);
    assert_eq!(p.blocks[2].programmed_time_s, 2.0);
    for (bad, needle) in [
        ("G0 X0 Y0\nG93 G1 X1 F1\nG1 X2\n", "own F word"),
        ("G0 X0 Y0\nG2 X1 Y1 K1 F10\n", "K word"),
        (
            "G0 X0 Y0\nG2 X4 Y0 R1.9 F10\n",
            "shorter than half the chord",
        ),
        ("G0 X0 Y0\nG2 X1 Y1.01 I1 J0 F10\n", "radius"),
        ("G0 X0\nG95 G1 X1 F0.1\n", "per revolution"),
        ("G1 X1 F10\n", "unknown position"),
        ("G0 X0\nG1 X1 F0\n", "not positive"),
        ("G0 X0\n(DWELL 0 1 S AT 0 0)\nG1 X1 F10\n", "END DWELL"),
        ("G0 X0\n(DWELL 0 one S AT 0 0)\n", "dwell marker"),
        ("G0 X0 (open comment\n", "never closed"),
        ("G0 X0\nG1 X1 Q5 F10\n", "word Q"),
    ] {
        let e = Program::parse(bad, Dialect::Iso).unwrap_err().to_string();
        assert!(e.contains(needle), "{bad:?}: {e}");
        assert!(e.starts_with("program line"), "{e}");
    }
}

#[test]
fn feeds_on_a_sphere_follow_the_tool_centre_path() {
    // Sphere R 25 mm (centre (0, 0, 25)), tool radius 5 mm, tool axis along the normal.
    // A tool centre is A = P + r n with n = (C - P) / R, i.e. A = C + (R - r)(P - C) / R.
    let r_sphere = 25.0;
    let r_tool = 5.0;
    let sphere = Surface::Conic(Conic {
        curvature_per_mm: 1.0 / r_sphere,
        conic: 0.0,
    });
    let path = DwellPath::new(vec![0.0, 4.0, 8.0, 12.0], vec![0.0, 2.0, 2.0, 6.0]).unwrap();
    let dwell = [0.8, 0.3, 1.1, 0.5];
    let s = NcSettings {
        tool_radius_mm: r_tool,
        tool_axis: ToolAxis::Normal,
        ..NcSettings::default()
    };
    let nc = NcProgram::plan(&path, &dwell, &sphere, &s).unwrap();
    let w = write_program(&nc, &[]).unwrap();
    let centre = |x: f64, y: f64| {
        let z = r_sphere - (r_sphere * r_sphere - x * x - y * y).sqrt();
        let k = (r_sphere - r_tool) / r_sphere;
        [k * x, k * y, r_sphere + k * (z - r_sphere)]
    };
    let (px, py) = (path.x_mm(), path.y_mm());
    let mid = |a: usize, b: usize| (0.5 * (px[a] + px[b]), 0.5 * (py[a] + py[b]));
    let dist = |a: [f64; 3], b: [f64; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let p = Program::parse(&w.text, Dialect::Iso).unwrap();
    let mut planar_gap = 0.0f64;
    for j in 0..4 {
        let (bx0, by0) = if j == 0 {
            (2.0 * px[0] - mid(0, 1).0, 2.0 * py[0] - mid(0, 1).1)
        } else {
            mid(j - 1, j)
        };
        let (bx1, by1) = if j == 3 {
            (2.0 * px[3] - mid(2, 3).0, 2.0 * py[3] - mid(2, 3).1)
        } else {
            mid(j, j + 1)
        };
        let a = centre(px[j], py[j]);
        let len = dist(centre(bx0, by0), a) + dist(a, centre(bx1, by1));
        let feed_hand = 60.0 * len / dwell[j];
        let b = &p.blocks[p.stretch_blocks(j)];
        let feed_prog = 60.0 * b[0].length_mm() / b[0].programmed_time_s;
        assert!(
            (feed_prog - feed_hand).abs() <= 2e-4 * feed_hand + 1e-3,
            "stretch {j}: {feed_prog} vs hand {feed_hand}"
        );
        planar_gap = planar_gap.max((feed_hand / nc.points[j].feed_mm_per_min - 1.0).abs());
    }
    // The 3-D tool-centre feed differs from the planar feed the engine plans with (the tool
    // centre runs on a sphere of radius R - r, 20% smaller): programming the planar feed would
    // get the dwell wrong by as much.
    assert!(planar_gap > 0.05, "{planar_gap}");
    // Contact points back from tool centres (the simulator's inversion).
    let pt = &nc.points[2];
    let (x, y) = contact_xy(&sphere, r_tool, pt.tool_mm).unwrap();
    assert!((x - pt.x_mm).abs() < 1e-8 && (y - pt.y_mm).abs() < 1e-8);
}

#[test]
fn programs_refuse_what_a_controller_cannot_run() {
    // 0.1 mm steps at 3000 mm/min: half-blocks of 1 ms, below the default 2 ms block time. On a
    // straight line each stretch becomes one 2 ms block through its point, still exact.
    let line = DwellPath::new(vec![0.0, 0.1, 0.2, 0.3], vec![0.0; 4]).unwrap();
    let fast = [0.002; 4];
    let nc = NcProgram::plan(&line, &fast, &Flat, &NcSettings::default()).unwrap();
    let w = write_program(&nc, &[]).unwrap();
    assert_eq!(w.merged_stretches, 4);
    let p = Program::parse(&w.text, Dialect::Iso).unwrap();
    for (k, t) in p.programmed_stretch_times_s().iter().enumerate() {
        assert_eq!(p.stretch_blocks(k).len(), 1);
        assert!((t - 0.002).abs() <= STRETCH_TOL * 0.002, "{t}");
    }
    // A zigzag cannot merge through its corners (the run-in stretch of point 0 is straight): the
    // first short block is named.
    let zig = DwellPath::new(vec![0.0, 0.1, 0.2, 0.3], vec![0.0, 0.1, 0.0, 0.1]).unwrap();
    let ds = zig.ds_mm();
    let fast: Vec<f64> = ds.iter().map(|d| 60.0 * d / 3000.0).collect();
    let nc = NcProgram::plan(&zig, &fast, &Flat, &NcSettings::default()).unwrap();
    let e = write_program(&nc, &[]).unwrap_err().to_string();
    assert!(e.contains("dwell point 1") && e.contains("2 ms"), "{e}");
    // A single point, or a repeated one with dwell: no path to sweep.
    let one = DwellPath::new(vec![1.0], vec![1.0]).unwrap();
    let nc = NcProgram::plan(&one, &[2.0], &Flat, &NcSettings::default()).unwrap();
    let e = write_program(&nc, &[]).unwrap_err().to_string();
    assert!(
        e.contains("dwell point 0") && e.contains("zero length"),
        "{e}"
    );
    let rep = DwellPath::new(vec![0.0, 1.0, 1.0, 1.0], vec![0.0; 4]).unwrap();
    let nc = NcProgram::plan(&rep, &[1.0, 1.0, 1.0, 1.0], &Flat, &NcSettings::default()).unwrap();
    let e = write_program(&nc, &[]).unwrap_err().to_string();
    assert!(
        e.contains("dwell point 2") && e.contains("zero length"),
        "{e}"
    );
    // v_max caps the programmed feed: the stretch is slowed, never over the limit.
    let path = DwellPath::new(vec![0.0, 1.0, 2.0], vec![0.0; 3]).unwrap();
    let s = NcSettings {
        v_max_mm_per_min: Some(100.0),
        ..NcSettings::default()
    };
    let nc = NcProgram::plan(&path, &[0.5, 0.5, 0.5], &Flat, &s).unwrap();
    let w = write_program(&nc, &[]).unwrap();
    assert_eq!(w.slowed_stretches, 3);
    assert!((w.max_slowdown - 1.2).abs() < 1e-9, "{}", w.max_slowdown);
    assert!(w.text.contains("F100.000") && !w.text.contains("F120"));
}

/// Hand-written circular moves read back against the closed forms: end points on the circle,
/// length `r theta`, time `60 L / F` (G94) or `60 / F` (G93), helix `sqrt((r theta)^2 + dz^2)`,
/// full circle `2 pi r`, in both dialect families.
#[test]
fn circular_moves_read_back_to_closed_forms() {
    use preston::solver::machine::gcode::program::ARC_RADIUS_TOLERANCE_MM;
    let pi = std::f64::consts::PI;
    for (d, g2, g3) in [
        (Dialect::Iso, "G02", "G03"),
        (Dialect::Fanuc, "G02", "G03"),
        (Dialect::Linuxcnc, "G2", "G3"),
        (Dialect::Sinumerik, "G2", "G3"),
    ] {
        let text = format!(
            "G17 G90 G94\nG0 X10 Y0 Z0\n{g3} X0 Y10 I-10 J0 F600\n{g2} X10 Y0 I0 J-10\n\
             {g3} X10 Y0 Z2 I-10 J0\nG93 {g3} X-10 Y0 I-10 J0 F30\n"
        );
        let p = Program::parse(&text, d).unwrap();
        let b = &p.blocks;
        assert_eq!(b[1].kind, BlockKind::Circular);
        // Quarter circle ccw, then back cw along the same quarter.
        for k in [1, 2] {
            assert!((b[k].length_mm() - 10.0 * pi / 2.0).abs() < 1e-12);
            assert!((b[k].programmed_time_s - 60.0 * 5.0 * pi / 600.0).abs() < 1e-12);
            for i in 0..=20 {
                let q = b[k].point_at(i as f64 / 20.0);
                assert!((q[0].hypot(q[1]) - 10.0).abs() < 1e-12);
                // First quadrant throughout.
                assert!(q[0] >= -1e-12 && q[1] >= -1e-12);
            }
        }
        let mid = b[1].point_at(0.5);
        assert!((mid[0] - 10.0 * (pi / 4.0).cos()).abs() < 1e-12);
        // Full helical turn: start = end in XY.
        let l = (2.0 * pi * 10.0f64).hypot(2.0);
        assert!((b[3].length_mm() - l).abs() < 1e-12);
        assert!((b[3].programmed_time_s - 60.0 * l / 600.0).abs() < 1e-12);
        // Inverse time: half circle in 2 s.
        assert!((b[4].length_mm() - 10.0 * pi).abs() < 1e-12);
        assert!((b[4].programmed_time_s - 2.0).abs() < 1e-12);
        // End radius off by more than the limit: refused naming the line.
        let bad = format!(
            "G0 X10 Y0 Z0\n{g3} X0 Y{} I-10 J0 F600\n",
            10.0 + 2.0 * ARC_RADIUS_TOLERANCE_MM
        );
        let e = Program::parse(&bad, d).unwrap_err().to_string();
        assert!(e.contains("line 2") || e.contains('2'), "{e}");
        assert!(Program::parse("G0 X10 Y0 Z0\nG3 X0 Y10 K10 F600\n", d).is_err());
    }
}

/// Largest distance between a radius-form centre and its closed form, mm.
const CENTRE_TOL_MM: f64 = 1e-12;

/// Sweep of the arc from `s` to `e` about `c`, turning counter-clockwise when `ccw`, radians in
/// (0, 2 pi], from the cross and dot products of the two radius vectors.
fn sweep_about(s: [f64; 2], e: [f64; 2], c: [f64; 2], ccw: bool) -> f64 {
    let (u, v) = ([s[0] - c[0], s[1] - c[1]], [e[0] - c[0], e[1] - c[1]]);
    let cross = u[0] * v[1] - u[1] * v[0];
    let dot = u[0] * v[0] + u[1] * v[1];
    let ccw_angle = cross.atan2(dot).rem_euclid(std::f64::consts::TAU);
    if ccw {
        ccw_angle
    } else {
        std::f64::consts::TAU - ccw_angle
    }
}

/// The radius form's centre: on the chord's bisector, at |R| from both ends, on the side that
/// makes the arc at most 180 degrees for R > 0 and more for R < 0, in both turning directions.
#[test]
fn radius_form_centres_follow_the_sign_rule() {
    use preston::solver::machine::gcode::program::{
        arc_centre_from_radius, RadiusArcError, ARC_RADIUS_TOLERANCE_MM,
    };
    let pi = std::f64::consts::PI;
    let close = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]) < CENTRE_TOL_MM;
    // Chord (0, 0) -> (8, 0), |R| = 5: the centre is 3 mm above or below the midpoint (3-4-5).
    let (s, e) = ([0.0, 0.0], [8.0, 0.0]);
    for (r, ccw, want) in [
        (5.0, true, [4.0, 3.0]),
        (-5.0, true, [4.0, -3.0]),
        (5.0, false, [4.0, -3.0]),
        (-5.0, false, [4.0, 3.0]),
    ] {
        let c = arc_centre_from_radius(s, e, r, ccw).unwrap();
        assert!(close(c, want), "R {r} ccw {ccw}: {c:?}");
    }
    // Any chord direction and radius: equidistant, and the sweep on the side of the sign.
    for k in 0..24 {
        let a = k as f64 * 0.37;
        let (s, e) = (
            [1.0 + 0.3 * k as f64, -2.0],
            [1.0 + 0.3 * k as f64 + 3.0 * a.cos(), -2.0 + 3.0 * a.sin()],
        );
        for r in [1.6, 2.5, 40.0, -1.6, -2.5, -40.0] {
            for ccw in [true, false] {
                let c = arc_centre_from_radius(s, e, r, ccw).unwrap();
                let d = |p: [f64; 2]| (p[0] - c[0]).hypot(p[1] - c[1]);
                assert!((d(s) - r.abs()).abs() < 1e-9 && (d(e) - r.abs()).abs() < 1e-9);
                let sweep = sweep_about(s, e, c, ccw);
                if r > 0.0 {
                    assert!(sweep <= pi, "R {r} ccw {ccw}: sweep {sweep}");
                } else {
                    assert!(sweep > pi, "R {r} ccw {ccw}: sweep {sweep}");
                }
            }
        }
    }
    // Half the chord: the half circle about the midpoint, also a rounding short of it.
    for r in [4.0, 4.0 - 0.5 * ARC_RADIUS_TOLERANCE_MM, -4.0] {
        let c = arc_centre_from_radius(s, e, r, true).unwrap();
        assert!(close(c, [4.0, 0.0]), "R {r}: {c:?}");
    }
    assert_eq!(
        arc_centre_from_radius(s, e, 4.0 - 2.0 * ARC_RADIUS_TOLERANCE_MM, true),
        Err(RadiusArcError::TooShort {
            radius_mm: 4.0 - 2.0 * ARC_RADIUS_TOLERANCE_MM,
            half_chord_mm: 4.0
        })
    );
    assert_eq!(
        arc_centre_from_radius(s, s, 5.0, true),
        Err(RadiusArcError::FullCircle)
    );
    assert_eq!(
        arc_centre_from_radius(s, e, 0.0, true),
        Err(RadiusArcError::ZeroRadius)
    );
}

/// Radius-form arcs read back to the same blocks as their I J form in every dialect (`CR=` on
/// Sinumerik), in inches too, and an impossible radius is refused naming its line.
#[test]
fn radius_form_arcs_read_as_their_centre_form_in_every_dialect() {
    // From (0, 0) to (8, 0) with |R| = 5: the minor arc (about 106.26 degrees) and the major one.
    let minor = 2.0 * 4.0f64.atan2(3.0);
    let tau = std::f64::consts::TAU;
    for d in Dialect::ALL {
        let r = |v: f64| {
            if d == Dialect::Sinumerik {
                format!("CR={v}")
            } else {
                format!("R{v}")
            }
        };
        let radius_form = format!(
            "G17 G90 G94\nG0 X0 Y0 Z0\nG3 X8 Y0 {} F600\nG3 X0 Y0 {}\nG2 X8 Y0 Z1 {}\n\
             G2 X0 Y0 {}\nG20\nG3 X0.1 Y0 {}\n",
            r(5.0),
            r(-5.0),
            r(-5.0),
            r(5.0),
            r(0.05)
        );
        let centre_form = "G17 G90 G94\nG0 X0 Y0 Z0\nG3 X8 Y0 I4 J3 F600\nG3 X0 Y0 I-4 J3\n\
             G2 X8 Y0 Z1 I4 J3\nG2 X0 Y0 I-4 J3\nG20\nG3 X0.1 Y0 I0.05 J0\n";
        let a = Program::parse(&radius_form, d).unwrap();
        let b = Program::parse(centre_form, d).unwrap();
        assert_eq!(a.blocks.len(), b.blocks.len());
        for (x, y) in a.blocks.iter().zip(&b.blocks) {
            assert_eq!((x.kind, x.line, x.end_mm), (y.kind, y.line, y.end_mm));
            let (cx, cy) = (x.arc.map(|a| a.centre_mm), y.arc.map(|a| a.centre_mm));
            match (cx, cy) {
                (Some(p), Some(q)) => {
                    assert!(
                        (p[0] - q[0]).hypot(p[1] - q[1]) < CENTRE_TOL_MM,
                        "{d:?} line {}",
                        x.line
                    );
                }
                (None, None) => {}
                other => panic!("{d:?} line {}: {other:?}", x.line),
            }
            assert!((x.programmed_time_s - y.programmed_time_s).abs() < 1e-12);
        }
        // Closed forms: 5 mm times the sweep; the major arc is the rest of the circle.
        let len: Vec<f64> = a.blocks.iter().map(|b| b.length_mm()).collect();
        assert!((len[1] - 5.0 * minor).abs() < 1e-12, "{d:?}");
        assert!((len[2] - 5.0 * (tau - minor)).abs() < 1e-12, "{d:?}");
        assert!(
            (len[3] - (5.0 * (tau - minor)).hypot(1.0)).abs() < 1e-12,
            "{d:?}"
        );
        assert!((len[4] - 5.0 * minor).abs() < 1e-12, "{d:?}");
        // 0.1 inch chord, 0.05 inch radius: the half circle, pi * 1.27 mm.
        assert!(
            (len[5] - std::f64::consts::PI * 1.27).abs() < 1e-12,
            "{d:?}"
        );
        // Impossible radii, naming the line.
        for (bad, needle) in [
            (r(3.9), "shorter than half the chord"),
            (r(0.0), "radius is zero"),
            (format!("{} I4 J3", r(5.0)), "not both"),
        ] {
            let text = format!("G0 X0 Y0 Z0\n(C)\nG3 X8 Y0 {bad} F600\n");
            let text = if d == Dialect::Sinumerik {
                text.replace("(C)", "; C")
            } else {
                text
            };
            let e = Program::parse(&text, d).unwrap_err().to_string();
            assert!(
                e.starts_with("program line 3:") && e.contains(needle),
                "{d:?}: {e}"
            );
        }
        let e = Program::parse("G0 X1 Y0 Z0\nG3 X1 Y0 R5 F600\n", d)
            .unwrap_err()
            .to_string();
        let want = if d == Dialect::Sinumerik {
            "CR="
        } else {
            "coincide"
        };
        assert!(
            e.starts_with("program line 2:") && e.contains(want),
            "{d:?}: {e}"
        );
    }
}

fn circle_path(r: f64, n: usize, turn: f64) -> DwellPath {
    let (x, y): (Vec<f64>, Vec<f64>) = (0..n)
        .map(|i| {
            let a = turn * i as f64 / (n - 1) as f64;
            (5.0 + r * a.cos(), -3.0 + r * a.sin())
        })
        .unzip();
    DwellPath::new(x, y).unwrap()
}

/// A dwell path with circular runs (a clockwise arc, a straight run, a counter-clockwise arc)
/// written with G02/G03: every stretch still takes its dwell in every dialect and feed mode, the
/// arcs are found, and the points written lie on their circles.
#[test]
fn arcs_keep_the_stretch_contract() {
    // Arc of radius 20 clockwise through 120 degrees, a straight leg, an arc of radius 8 ccw.
    let a = circle_path(20.0, 60, -2.0 * std::f64::consts::PI / 3.0);
    let (mut x, mut y) = (a.x_mm().to_vec(), a.y_mm().to_vec());
    let (lx, ly) = (x[x.len() - 1], y[y.len() - 1]);
    for i in 1..10 {
        x.push(lx + 0.7 * i as f64);
        y.push(ly);
    }
    let (sx, sy) = (x[x.len() - 1], y[y.len() - 1]);
    for i in 1..40 {
        let t = std::f64::consts::PI * i as f64 / 40.0;
        x.push(sx + 8.0 * t.sin());
        y.push(sy + 8.0 - 8.0 * t.cos());
    }
    let path = DwellPath::new(x, y).unwrap();
    let dwell: Vec<f64> = (0..path.len())
        .map(|j| 0.2 + 0.9 * ((j * 7) % 11) as f64 / 11.0)
        .collect();
    for d in Dialect::ALL {
        for m in MODES {
            let s = NcSettings {
                arc_tolerance_mm: Some(1e-3),
                ..settings(d, m)
            };
            assert_delivers(&path, &dwell, &Flat, &s);
            let nc = NcProgram::plan(&path, &dwell, &Flat, &s).unwrap();
            let w = write_program(&nc, &[]).unwrap();
            assert_eq!(w.arc_runs, 2, "{d:?}");
            // Each run of k points gives 2 (k - 1) circular blocks.
            assert_eq!(w.arc_blocks, 2 * 59 + 2 * 39, "{d:?}");
            let p = Program::parse(&w.text, d).unwrap();
            let mut arc_len = 0.0;
            for b in p.blocks.iter().filter(|b| b.kind == BlockKind::Circular) {
                let a = b.arc.unwrap();
                let first = (a.centre_mm[0] - 5.0).hypot(a.centre_mm[1] + 3.0) < 1e-2;
                let r = if first { 20.0 } else { 8.0 };
                for f in [0.0, 0.5, 1.0] {
                    let q = b.point_at(f);
                    assert!(
                        ((q[0] - a.centre_mm[0]).hypot(q[1] - a.centre_mm[1]) - r).abs() < 2e-4
                    );
                }
                if first {
                    arc_len += b.length_mm();
                    assert!(!a.ccw);
                } else {
                    assert!(a.ccw);
                }
            }
            // The first run's blocks cover its 120 degrees from point 0 to point 59: r theta.
            let expect = 20.0 * 2.0 * std::f64::consts::PI / 3.0;
            assert!((arc_len - expect).abs() < 1e-3, "{arc_len} vs {expect}");
        }
    }
}

/// The removal of an arcs program executed and integrated equals that of the straight program
/// (the arcs depart from the chords by their sagitta only).
#[test]
fn arcs_program_removes_what_the_straight_one_does() {
    use preston::solver::observer::Silent;
    use preston::solver::simulate::program::run_on_map;
    use preston::solver::tif::gaussian::GaussianTif;
    let path = circle_path(15.0, 181, 2.0 * std::f64::consts::PI * 0.99);
    let dwell: Vec<f64> = (0..path.len())
        .map(|j| 0.5 + 0.4 * (j as f64 * 0.21).sin())
        .collect();
    let tif = GaussianTif::new(1.5, 10.0, 4.5).unwrap();
    let (mut mx, mut my) = (Vec::new(), Vec::new());
    for i in 0..81 {
        for k in 0..81 {
            mx.push(-15.0 + 0.5 * i as f64);
            my.push(-23.0 + 0.5 * k as f64);
        }
    }
    let mut removal = Vec::new();
    for arcs in [None, Some(1e-3)] {
        let s = NcSettings {
            arc_tolerance_mm: arcs,
            ..settings(Dialect::Iso, FeedMode::PerMinute)
        };
        let nc = NcProgram::plan(&path, &dwell, &Flat, &s).unwrap();
        let w = write_program(&nc, &[]).unwrap();
        assert_eq!(w.arc_blocks > 0, arcs.is_some());
        let p = Program::parse(&w.text, Dialect::Iso).unwrap();
        let run = run_on_map(
            &p,
            Kinematics::ProgrammedFeed,
            0.05,
            None,
            0.0,
            &|samples| {
                preston::solver::simulate::direct::removal_of_samples(
                    &mx, &my, samples, &tif, &Silent,
                )
            },
        )
        .unwrap();
        removal.push(run.removal_nm);
    }
    let rms = |v: &[f64]| (v.iter().map(|a| a * a).sum::<f64>() / v.len() as f64).sqrt();
    let diff: Vec<f64> = removal[0]
        .iter()
        .zip(&removal[1])
        .map(|(a, b)| a - b)
        .collect();
    let rel = rms(&diff) / rms(&removal[0]);
    assert!(
        rms(&removal[0]) > 1.0 && rel < 1e-3,
        "relative RMS difference {rel}"
    );
}

/// The rules of each controller's manual that a program must keep, checked on the text alone
/// (independently of the writer and of the reader):
/// - ISO 6983 / Fanuc / LinuxCNC: `( )` comments that hold no `(`, `;` or `%` (`;` ends a block
///   on Fanuc, `%` ends the record on ISO tapes); Sinumerik: `;` comments, no parentheses
///   anywhere, `%_N_<NAME>_MPF` first (Sinumerik 840D sl programming manual, "Program name");
/// - Fanuc: `%`, then `O` and four digits, every axis word with a decimal point, at most one M
///   code per block (the default of parameter 3404), `N` at most five digits;
/// - every program: the safe-start block first, a work offset, `G94` back in force before the
///   program end when `G93` was used, the end word last (`M2` on LinuxCNC, `M30` elsewhere).
fn manual_rules(text: &str, d: Dialect, inverse_time: bool) -> Vec<String> {
    let mut bad = Vec::new();
    let lines: Vec<&str> = text.lines().collect();
    let (first, last) = (lines[0], lines[lines.len() - 1]);
    match d {
        Dialect::Sinumerik => {
            let name = first
                .strip_prefix("%_N_")
                .and_then(|r| r.strip_suffix("_MPF"))
                .unwrap_or("");
            if name.len() < 2
                || !name
                    .chars()
                    .all(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_')
            {
                bad.push(format!("first line {first}"));
            }
            if text.contains('(') || text.contains(')') {
                bad.push("parenthesis".into());
            }
        }
        _ => {
            if first != "%" || last != "%" {
                bad.push("not % wrapped".into());
            }
        }
    }
    if d == Dialect::Fanuc {
        let o = lines[1];
        if !(o.len() == 5 && o.starts_with('O') && o[1..].chars().all(|c| c.is_ascii_digit())) {
            bad.push(format!("program number line {o}"));
        }
    }
    let mut code_lines = Vec::new();
    for l in &lines {
        if d == Dialect::Sinumerik {
            if let Some(at) = l.find(';') {
                code_lines.push(&l[..at]);
                continue;
            }
        } else if let Some(open) = l.find('(') {
            let close = l.rfind(')').unwrap_or(0);
            let inner = &l[open + 1..close.max(open + 1)];
            if close <= open || inner.contains(['(', ';', '%']) {
                bad.push(format!("comment {l}"));
            }
            code_lines.push(&l[..open]);
            continue;
        }
        // `%` lines and the Fanuc program-number line carry no block.
        if l.starts_with('%') || (d == Dialect::Fanuc && l.starts_with('O')) {
            continue;
        }
        code_lines.push(l);
    }
    let blocks: Vec<Vec<&str>> = code_lines
        .iter()
        .map(|l| l.split_whitespace().collect::<Vec<_>>())
        .filter(|w: &Vec<&str>| !w.is_empty())
        .collect();
    let words = |b: &Vec<&str>| -> Vec<String> {
        b.iter()
            .filter(|w| !w.starts_with('N') && !w.starts_with('O'))
            .map(|w| w.to_string())
            .collect()
    };
    if words(&blocks[0]).join(" ") != d.safe_start() {
        bad.push(format!("first block {:?}", blocks[0]));
    }
    if !blocks.iter().any(|b| b.contains(&"G54")) {
        bad.push("no work offset".into());
    }
    let end = d.program_end();
    if words(blocks.last().unwrap()) != [end] {
        bad.push(format!("last block {:?}", blocks.last()));
    }
    let feed_modes: Vec<&str> = blocks
        .iter()
        .flatten()
        .copied()
        .filter(|w| *w == "G93" || *w == "G94")
        .collect();
    if feed_modes.last() != Some(&"G94") || feed_modes.contains(&"G93") != inverse_time {
        bad.push(format!("feed modes {feed_modes:?}"));
    }
    for b in &blocks {
        if d == Dialect::Fanuc {
            if b.iter().filter(|w| w.starts_with('M')).count() > 1 {
                bad.push(format!("several M codes in {b:?}"));
            }
            for w in b {
                let axis = w.starts_with(['X', 'Y', 'Z', 'B', 'I', 'J']);
                if axis && !w.contains('.') {
                    bad.push(format!("no decimal point in {w}"));
                }
                if w.starts_with('N') && w.len() > 6 {
                    bad.push(format!("block number {w}"));
                }
            }
        }
    }
    bad
}

#[test]
fn every_dialect_keeps_its_manual_rules_and_sane_comment_digits() {
    let path = serpentine(6, 3, 1.0);
    let dwell: Vec<f64> = (0..18).map(|j| 0.1 + 0.1 / 3.0 * j as f64).collect();
    for d in Dialect::ALL {
        for m in MODES {
            let s = NcSettings {
                spindle_rpm: Some(600.4),
                coolant: Coolant::Mist,
                ..settings(d, m)
            };
            let nc = NcProgram::plan(&path, &dwell, &Flat, &s).unwrap();
            // A note with every character a comment must not hold.
            let w = write_program(&nc, &["JOB a;b (c) 5% \u{b0}".into()]).unwrap();
            let bad = manual_rules(&w.text, d, m == FeedMode::InverseTime);
            assert!(bad.is_empty(), "{d:?} {m:?}: {bad:?}\n{}", w.text);
            assert!(w.text.contains("S600 M3") && w.text.contains("M7"));
            // Numbers in comments: at most 9 decimals and 10 significant digits.
            for l in w.text.lines().filter(|l| l.contains("DWELL ")) {
                for tok in l.split([' ', '(', ')', ';']) {
                    if let Some((int, frac)) = tok.split_once('.') {
                        let digits = int.trim_start_matches('-').len() + frac.len();
                        assert!(frac.len() <= 9 && digits <= 10, "{l}");
                    }
                }
            }
            // The reader takes it back with every marker.
            let p = Program::parse(&w.text, d).unwrap();
            assert_eq!(p.stretches.len(), 18);
        }
    }
    // The profile's own start and end blocks, work offset, program number and name.
    let s = NcSettings {
        start_blocks: Some(vec![
            "G17 G21 G40 G49 G80 G90".into(),
            "T1 M6".into(),
            "G43 H1".into(),
        ]),
        end_blocks: vec!["G40 G49".into()],
        work_offset: WorkOffset::G56,
        program_number: 42,
        ..settings(Dialect::Fanuc, FeedMode::InverseTime)
    };
    s.validate().unwrap();
    let nc = NcProgram::plan(&path, &dwell, &Flat, &s).unwrap();
    let text = write_program(&nc, &[]).unwrap().text;
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(&lines[..2], &["%", "O0042"]);
    let code: Vec<&&str> = lines.iter().filter(|l| l.starts_with('N')).collect();
    assert_eq!(code[0], &"N1 G17 G21 G40 G49 G80 G90");
    assert_eq!(code[1], &"N2 T1 M6");
    assert_eq!(code[3], &"N4 G17 G21 G56 G90 G93");
    assert!(code[code.len() - 2].ends_with("G40 G49"));
    let s = NcSettings {
        program_name: "Mirror_7".into(),
        ..settings(Dialect::Sinumerik, FeedMode::PerMinute)
    };
    let text = write_program(&NcProgram::plan(&path, &dwell, &Flat, &s).unwrap(), &[])
        .unwrap()
        .text;
    assert!(
        text.starts_with("%_N_MIRROR_7_MPF\n;$PATH=/_N_MPF_DIR\n"),
        "{text}"
    );
}
