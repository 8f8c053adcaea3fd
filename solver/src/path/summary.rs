//! What `preston path` prints (JSON) and the Python package's `path_*` functions return: one
//! summary per kind of path, built here once for both faces.
//!
//! Counts and lengths are of the path as written: its points after projection onto the part
//! ([`ProjectedPath`]), its length the sum of their `ds_mm`.

use super::chord_height::ChordHeightPath;
use super::edge_offset::{EdgeOffsetPath, OffsetLine};
use super::intersection::iteration_pattern;
use super::random::{RandomPath, RandomPathSettings};
use super::raster::RasterAxis;
use super::ProjectedPath;
use serde::Serialize;

/// The summary of a generated path, tagged by its `kind`.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum PathSummary {
    /// A serpentine raster.
    Raster {
        /// Points written.
        points: usize,
        /// Raster lines.
        lines: usize,
        /// Path length, mm.
        length_mm: f64,
    },
    /// One iteration of the alternating (intersecting) rasters.
    Intersection {
        /// The iteration (0-based).
        iteration: usize,
        /// Direction of its lines.
        along: RasterAxis,
        /// Shift of its lines across themselves, mm (half a pitch on every other pass).
        shift_mm: f64,
        /// Points written.
        points: usize,
        /// Raster lines.
        lines: usize,
    },
    /// An Archimedes spiral.
    Spiral {
        /// Points written.
        points: usize,
        /// Turns: radius over pitch.
        turns: f64,
        /// Path length, mm.
        length_mm: f64,
    },
    /// Equal chord-height points along a line.
    ChordHeight {
        /// Points written.
        points: usize,
        /// Shortest step, mm.
        min_step_mm: f64,
        /// Longest step, mm.
        max_step_mm: f64,
        /// Smallest chord height of the steps before the last, um (null with fewer than two).
        min_chord_height_um: f64,
        /// Largest chord height, um.
        max_chord_height_um: f64,
        /// Chord height of the last (shortened) step, um.
        last_chord_height_um: f64,
        /// Length of the last step, mm.
        last_step_mm: f64,
    },
    /// The lifting-bonnet edge-offset trajectory.
    EdgeOffset {
        /// Points written.
        points: usize,
        /// Cubic Bezier segments of the fitted edge.
        bezier_segments: usize,
        /// Largest distance of the edge points to the fitted curve, mm.
        bezier_max_error_mm: f64,
        /// Corners of the edge.
        corners: usize,
        /// The offset lines, innermost first.
        lines: Vec<OffsetLine>,
        /// Index of each line's first point.
        line_starts: Vec<usize>,
    },
    /// A pseudo-random unicursal path.
    Random {
        /// Points written.
        points: usize,
        /// Grid nodes visited along x and y.
        nodes: [usize; 2],
        /// Grid nodes of the region along x and y.
        region_nodes: [usize; 2],
        /// Longest straight run, steps.
        longest_run: usize,
        /// Tree edges exchanged to meet the longest run allowed.
        tree_exchanges: usize,
        /// Seed of the generator.
        seed: u64,
        /// Jitter, fraction of the pitch.
        jitter: f64,
        /// Path length, mm (when the path was projected and written).
        #[serde(skip_serializing_if = "Option::is_none")]
        length_mm: Option<f64>,
    },
}

/// The length of a written path, mm.
fn length_mm(p: &ProjectedPath) -> f64 {
    p.ds_mm.iter().sum()
}

impl PathSummary {
    /// A raster of `lines` lines written as `p`.
    pub fn raster(p: &ProjectedPath, lines: usize) -> Self {
        PathSummary::Raster {
            points: p.len(),
            lines,
            length_mm: length_mm(p),
        }
    }

    /// Iteration `iteration` of the intersecting rasters at `pitch_mm`, `lines` lines written as
    /// `p`.
    pub fn intersection(p: &ProjectedPath, iteration: usize, pitch_mm: f64, lines: usize) -> Self {
        let (along, shifted) = iteration_pattern(iteration);
        PathSummary::Intersection {
            iteration,
            along,
            shift_mm: if shifted { 0.5 * pitch_mm } else { 0.0 },
            points: p.len(),
            lines,
        }
    }

    /// A spiral of `radius_mm` and `pitch_mm` between turns written as `p`.
    pub fn spiral(p: &ProjectedPath, radius_mm: f64, pitch_mm: f64) -> Self {
        PathSummary::Spiral {
            points: p.len(),
            turns: radius_mm / pitch_mm,
            length_mm: length_mm(p),
        }
    }

    /// The chord-height line `c` written as `p`.
    pub fn chord_height(p: &ProjectedPath, c: &ChordHeightPath) -> Self {
        let hs = &c.chord_heights_mm;
        let inner = &hs[..hs.len().saturating_sub(1)];
        PathSummary::ChordHeight {
            points: p.len(),
            min_step_mm: c.min_step_mm(),
            max_step_mm: c.max_step_mm(),
            min_chord_height_um: inner.iter().copied().fold(f64::INFINITY, f64::min) * 1e3,
            max_chord_height_um: hs.iter().copied().fold(0.0, f64::max) * 1e3,
            last_chord_height_um: hs.last().copied().unwrap_or(0.0) * 1e3,
            last_step_mm: c.steps_mm.last().copied().unwrap_or(0.0),
        }
    }

    /// The edge-offset trajectory `t` of `points` points.
    pub fn edge_offset(points: usize, t: &EdgeOffsetPath) -> Self {
        PathSummary::EdgeOffset {
            points,
            bezier_segments: t.edge.len(),
            bezier_max_error_mm: t.fit_error_mm,
            corners: t.corners,
            lines: t.lines.clone(),
            line_starts: t.line_starts.clone(),
        }
    }

    /// The random path `r` made with `settings`; `written`: the path as written, when it was.
    pub fn random(
        r: &RandomPath,
        settings: &RandomPathSettings,
        written: Option<&ProjectedPath>,
    ) -> Self {
        PathSummary::Random {
            points: written.map_or(r.path.len(), ProjectedPath::len),
            nodes: r.nodes,
            region_nodes: r.region_nodes,
            longest_run: r.longest_run,
            tree_exchanges: r.swaps,
            seed: settings.seed,
            jitter: settings.jitter,
            length_mm: written.map(length_mm),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::path::{project, DwellPath};

    /// A flat path of three points, 1 mm then 2 mm apart.
    fn written() -> ProjectedPath {
        let p = DwellPath::new(vec![0.0, 1.0, 3.0], vec![0.0; 3]).unwrap();
        project(&p, None).unwrap()
    }

    #[test]
    fn lengths_are_the_written_ds_and_the_kind_is_the_tag() {
        let p = written();
        let v = serde_json::to_value(PathSummary::raster(&p, 1)).unwrap();
        assert_eq!(v["kind"], "raster");
        assert_eq!(v["points"], 3);
        let ds: f64 = p.ds_mm.iter().sum();
        assert_eq!(v["length_mm"].as_f64().unwrap(), ds);
        // Steps of 1 and 2 mm: the ends take their full step, the middle point half of each,
        // 1 + 1.5 + 2.
        assert!((ds - 4.5).abs() < 1e-12, "{ds}");
    }

    #[test]
    fn intersection_iterations_alternate_axes_and_shift_every_other_pair() {
        let p = written();
        let along_shift = |k| {
            let v = serde_json::to_value(PathSummary::intersection(&p, k, 0.4, 2)).unwrap();
            (
                v["along"].as_str().unwrap().to_string(),
                v["shift_mm"].as_f64().unwrap(),
            )
        };
        assert_eq!(along_shift(0), ("x".into(), 0.0));
        assert_eq!(along_shift(1), ("y".into(), 0.0));
        assert_eq!(along_shift(2), ("x".into(), 0.2));
        assert_eq!(along_shift(3), ("y".into(), 0.2));
    }

    #[test]
    fn chord_heights_are_in_um_and_the_last_step_is_apart() {
        let p = written();
        let c = ChordHeightPath {
            path: DwellPath::new(vec![0.0, 0.0, 0.0], vec![0.0, 1.0, 3.0]).unwrap(),
            steps_mm: vec![1.0, 2.0],
            chord_heights_mm: vec![0.004, 0.001],
        };
        let v = serde_json::to_value(PathSummary::chord_height(&p, &c)).unwrap();
        assert_eq!(v["kind"], "chord_height");
        // The minimum is over the steps before the last (the last is shortened to the end).
        assert!((v["min_chord_height_um"].as_f64().unwrap() - 4.0).abs() < 1e-12);
        assert!((v["max_chord_height_um"].as_f64().unwrap() - 4.0).abs() < 1e-12);
        assert!((v["last_chord_height_um"].as_f64().unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(v["last_step_mm"], 2.0);
        // With one step there is no step before the last: null.
        let one = ChordHeightPath {
            path: DwellPath::new(vec![0.0, 0.0], vec![0.0, 1.0]).unwrap(),
            steps_mm: vec![1.0],
            chord_heights_mm: vec![0.002],
        };
        let v = serde_json::to_value(PathSummary::chord_height(&p, &one)).unwrap();
        assert!(v["min_chord_height_um"].is_null());
    }
}
