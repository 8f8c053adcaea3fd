//! The lines of a dwell path: segment lengths, turn angles, the corners at which the path
//! splits into lines (connecting moves carry no acceleration constraint, the machine stops
//! there) and the acceleration of each segment under constant acceleration between dwell points.

use crate::path::DwellPath;

/// Segment lengths `s_j = |P_{j+1} - P_j|`, mm (n - 1 entries).
pub fn segment_lengths_mm(path: &DwellPath) -> Vec<f64> {
    path.x_mm()
        .windows(2)
        .zip(path.y_mm().windows(2))
        .map(|(x, y)| match (x, y) {
            ([x0, x1], [y0, y1]) => (x1 - x0).hypot(y1 - y0),
            _ => 0.0,
        })
        .collect()
}

/// Turn angle of the path at each point, degrees: the angle between the incoming and outgoing
/// segments (0 at the two ends and where a segment has zero length).
pub fn turn_angles_deg(path: &DwellPath) -> Vec<f64> {
    let (x, y) = (path.x_mm(), path.y_mm());
    let n = path.len();
    let mut out = vec![0.0; n];
    for j in 1..n.saturating_sub(1) {
        let (ax, ay) = (x[j] - x[j - 1], y[j] - y[j - 1]);
        let (bx, by) = (x[j + 1] - x[j], y[j + 1] - y[j]);
        let (la, lb) = (ax.hypot(ay), bx.hypot(by));
        if la > 0.0 && lb > 0.0 {
            let c = ((ax * bx + ay * by) / (la * lb)).clamp(-1.0, 1.0);
            out[j] = c.acos().to_degrees();
        }
    }
    out
}

/// For each segment `(j, j+1)`: true when it carries the acceleration constraint, false for a
/// connecting move (the path turns by more than `corner_angle_deg` at both of its ends).
pub fn constrained_segments(path: &DwellPath, corner_angle_deg: f64) -> Vec<bool> {
    let turn = turn_angles_deg(path);
    turn.windows(2)
        .map(|w| !(w[0] > corner_angle_deg && w[1] > corner_angle_deg))
        .collect()
}

/// Acceleration of each segment under constant acceleration between dwell points,
/// `a_j = |v_{j+1}^2 - v_j^2| / (2 s_j)` with `v = ds / t`, mm/s^2; `None` for connecting moves,
/// zero-length segments and dwell times that are not positive.
pub fn segment_accelerations_mm_per_s2(
    path: &DwellPath,
    dwell_s: &[f64],
    corner_angle_deg: f64,
) -> Vec<Option<f64>> {
    let ds = path.ds_mm();
    let seg = segment_lengths_mm(path);
    let cons = constrained_segments(path, corner_angle_deg);
    let v2 = |j: usize| -> Option<f64> {
        let t = *dwell_s.get(j)?;
        let d = *ds.get(j)?;
        (t > 0.0).then(|| (d / t) * (d / t))
    };
    (0..seg.len())
        .map(|j| {
            if !cons[j] || seg[j] <= 0.0 {
                return None;
            }
            Some((v2(j + 1)? - v2(j)?).abs() / (2.0 * seg[j]))
        })
        .collect()
}

/// Largest segment acceleration (see [`segment_accelerations_mm_per_s2`]), mm/s^2; 0 if none.
pub fn max_acceleration_mm_per_s2(path: &DwellPath, dwell_s: &[f64], corner_angle_deg: f64) -> f64 {
    segment_accelerations_mm_per_s2(path, dwell_s, corner_angle_deg)
        .into_iter()
        .flatten()
        .fold(0.0, f64::max)
}
