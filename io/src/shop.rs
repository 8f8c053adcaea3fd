//! `preston shop`: a virtual shop for a measured part. The shop keeps the true surface; it runs a
//! program with the tool it really has ([`preston_solver::iterate::shop::ShopTool`]) and reads
//! the part with its interferometer (noise, piston and tilt dropped), so the whole
//! measure-calibrate-plan-polish loop can be rehearsed with the commands a shop runs.

use crate::atomic::commit_all;
use crate::calibration::{contact_motion, tif_grid};
use crate::error::{Error, Result};
use crate::metrology::MapSource;
use crate::simulation::read_program;
use crate::writers::{stage_json, stage_map_csv};
use preston_solver::calibrate::SpotFootprint;
use preston_solver::iterate::shop::{FootprintFigures, Interferometer, ShopTool};
use preston_solver::machine::gcode::dialect::Dialect;
use preston_solver::machine::gcode::motion::Kinematics;
use preston_solver::rng::SplitMix64;
use preston_solver::tif::Tif;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Removal samples per footprint radius along the executed motion.
const SAMPLES_PER_RADIUS: f64 = 48.0;

/// What one visit to the virtual shop reads.
#[derive(Debug, Clone)]
pub struct ShopInputs {
    /// The part's true surface before the run.
    pub surface: MapSource,
    /// The program to run (none: only measure).
    pub program: Option<PathBuf>,
    /// Its dialect.
    pub dialect: Option<Dialect>,
    /// The spot test the shop's true tool differs from.
    pub tif: Tif,
    /// How the controller runs the program.
    pub kinematics: Kinematics,
    /// The tool the shop really has.
    pub tool: ShopTool,
    /// The shop's interferometer.
    pub interferometer: Interferometer,
    /// Seed of the interferometer's noise.
    pub seed: u64,
}

/// What the shop leaves: the true surface after the run and what the interferometer reads.
#[derive(Debug, Clone)]
pub struct ShopVisit {
    /// Points, mm.
    pub x_mm: Vec<f64>,
    /// Points, mm.
    pub y_mm: Vec<f64>,
    /// The true surface after the run, nm.
    pub surface_after_nm: Vec<f64>,
    /// The interferometer's reading of it, nm (piston and tilt dropped).
    pub measured_nm: Vec<f64>,
    /// The record written as `shop.json`.
    pub record: ShopRecord,
}

/// `shop.json`: the true tool and what the run did.
#[derive(Debug, Clone, Serialize)]
pub struct ShopRecord {
    /// The tool as set.
    pub tool: ShopTool,
    /// Its footprint's figures against the spot test (what a calibration should find).
    pub tool_figures: FootprintFigures,
    /// Interferometer noise, nm RMS.
    pub noise_rms_nm: f64,
    /// Executed program time, s (0 without a program).
    pub program_time_s: f64,
    /// RMS of the true surface before and after (piston and tilt removed), nm.
    pub true_rms_before_nm: f64,
    /// After, nm.
    pub true_rms_after_nm: f64,
    /// RMS of the interferometer's reading, nm.
    pub measured_rms_nm: f64,
}

fn rms_without_plane(x: &[f64], y: &[f64], z: &[f64]) -> Result<f64> {
    let mut z = z.to_vec();
    preston_solver::map::remove_plane(x, y, &mut z).map_err(Error::Solver)?;
    Ok((z.iter().map(|v| v * v).sum::<f64>() / z.len().max(1) as f64).sqrt())
}

/// Runs the program with the shop's tool on the true surface and measures the result.
pub fn visit(inputs: &ShopInputs) -> Result<ShopVisit> {
    inputs.tool.validate().map_err(Error::Solver)?;
    let surface_file = inputs.surface.file.clone().unwrap_or_default();
    let map = inputs.surface.read()?.map;
    let spot = SpotFootprint::new(tif_grid(&inputs.tif)?).map_err(Error::Solver)?;
    let (x, y) = (map.x_mm().to_vec(), map.y_mm().to_vec());
    let mut surface = map.z_nm().to_vec();
    let mut program_time_s = 0.0;
    if let Some(program_file) = &inputs.program {
        let program = read_program(program_file, inputs.dialect)?;
        let (motion, time_s) = contact_motion(
            &program,
            inputs.kinematics,
            spot.radius_mm() / SAMPLES_PER_RADIUS,
        )
        .map_err(|e| Error::engine(program_file, e))?;
        program_time_s = time_s;
        let removal = inputs
            .tool
            .removal_nm(&spot, &motion, &x, &y)
            .map_err(|e| Error::engine(program_file, e))?;
        for (s, h) in surface.iter_mut().zip(&removal) {
            *s -= h;
        }
    }
    let mut rng = SplitMix64::new(inputs.seed);
    let measured = inputs
        .interferometer
        .measure(&x, &y, &surface, &mut rng)
        .map_err(|e| Error::engine(&surface_file, e))?;
    let record = ShopRecord {
        tool: inputs.tool,
        tool_figures: inputs.tool.figures(&spot),
        noise_rms_nm: inputs.interferometer.noise_rms_nm,
        program_time_s,
        true_rms_before_nm: rms_without_plane(&x, &y, map.z_nm())?,
        true_rms_after_nm: rms_without_plane(&x, &y, &surface)?,
        measured_rms_nm: rms_without_plane(&x, &y, &measured)?,
    };
    Ok(ShopVisit {
        x_mm: x,
        y_mm: y,
        surface_after_nm: surface,
        measured_nm: measured,
        record,
    })
}

/// Writes `surface_after.csv` (the true surface, for the next visit), `measured.csv` (what the
/// shop's interferometer reads) and `shop.json`, all or none.
pub fn write_visit(visit: &ShopVisit, out_dir: &Path) -> Result<()> {
    std::fs::create_dir_all(out_dir).map_err(|e| Error::io(out_dir, e))?;
    commit_all(vec![
        stage_map_csv(
            &out_dir.join("surface_after.csv"),
            &visit.x_mm,
            &visit.y_mm,
            &visit.surface_after_nm,
        )?,
        stage_map_csv(
            &out_dir.join("measured.csv"),
            &visit.x_mm,
            &visit.y_mm,
            &visit.measured_nm,
        )?,
        stage_json(&out_dir.join("shop.json"), &visit.record)?,
    ])
}
