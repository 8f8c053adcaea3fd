//! Zero-removal guard band.
//!
//! The extension points get the map's lowest height, `z_ext = min_i z_i`. With the free piston
//! `c` the least-removal plan removes `z - min z` on the map, so the band asks for no removal
//! beyond the uniform layer: dwell that spills over the edge shows up as residual there, and the
//! optimiser keeps the dwell beyond the aperture down to what the rim needs. This is the
//! sacrificial guard band of sub-aperture polishing practice (material beyond the clear
//! aperture that is to be left alone), written as a least-squares target.

/// Target heights of `n` band points: the map's minimum height, nm (0 for an empty map).
pub fn extend(map_z_nm: &[f64], n: usize) -> Vec<f64> {
    let lo = map_z_nm.iter().copied().fold(f64::INFINITY, f64::min);
    vec![if lo.is_finite() { lo } else { 0.0 }; n]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn band_holds_the_least_removal_level() {
        let z = [3.0, -2.5, 7.0];
        let e = extend(&z, 4);
        assert_eq!(e, vec![-2.5; 4]);
        // Removal target z - min z is zero at the band and non-negative on the map.
        assert!(z.iter().all(|&v| v - e[0] >= 0.0));
    }
}
