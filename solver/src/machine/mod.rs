//! Machine dynamics and output for CAM: feed schedules and machining time ([`feeds`]), G-code and
//! point lists ([`nc`]), normal-displacement compensation ([`compensation`]) and programs for
//! rotationally symmetric aspheres ([`asphere`]).
//!
//! Units: lengths mm, time s, feeds mm/min, accelerations mm/s^2, speeds rpm, forces N,
//! moduli GPa.

pub mod asphere;
pub mod compensation;
pub mod feeds;
pub mod gcode;
pub mod geometry;
pub mod machinability;
pub mod nc;
pub mod profile;
pub mod words;

use crate::error::Result;

/// The part surface as the NC writer needs it: sag, normal and local curvature radius at a plan
/// position. Implemented for a flat part ([`Flat`]) and for the freeform surfaces of the engine.
pub trait PartGeometry {
    /// Surface height `z(x, y)`, mm.
    fn sag_mm(&self, x_mm: f64, y_mm: f64) -> Result<f64>;
    /// Unit normal pointing away from the part (towards the tool), `(nx, ny, nz)`, `nz > 0`.
    fn unit_normal(&self, x_mm: f64, y_mm: f64) -> Result<[f64; 3]>;
    /// Local radius of curvature used by the contact model, mm (the smallest principal radius;
    /// `+inf` where the surface is flat).
    fn curvature_radius_mm(&self, x_mm: f64, y_mm: f64) -> Result<f64>;
}

/// A flat part in the plane `z = 0`: normal `(0, 0, 1)`, infinite curvature radius.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Flat;

impl PartGeometry for Flat {
    fn sag_mm(&self, _x_mm: f64, _y_mm: f64) -> Result<f64> {
        Ok(0.0)
    }
    fn unit_normal(&self, _x_mm: f64, _y_mm: f64) -> Result<[f64; 3]> {
        Ok([0.0, 0.0, 1.0])
    }
    fn curvature_radius_mm(&self, _x_mm: f64, _y_mm: f64) -> Result<f64> {
        Ok(f64::INFINITY)
    }
}

/// Formats `v` with `decimals` places, without a negative zero.
pub(crate) fn fixed(v: f64, decimals: usize) -> String {
    let s = format!("{v:.decimals$}");
    if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') {
        s[1..].to_string()
    } else {
        s
    }
}

/// Formats `v` with at most `decimals` places, trailing zeros (and a trailing point) removed:
/// `10.00` -> `10`, `0.0600` -> `0.06`.
pub(crate) fn trimmed(v: f64, decimals: usize) -> String {
    let s = fixed(v, decimals);
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn number_formats() {
        assert_eq!(fixed(-0.00001, 4), "0.0000");
        assert_eq!(fixed(-1.5, 2), "-1.50");
        assert_eq!(trimmed(10.0, 2), "10");
        assert_eq!(trimmed(0.06, 4), "0.06");
        assert_eq!(trimmed(9.39, 2), "9.39");
        assert_eq!(trimmed(-0.00001, 4), "0");
    }
}
