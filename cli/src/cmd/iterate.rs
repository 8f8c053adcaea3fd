//! `preston iterate`: the measure-register-solve-polish loop on a virtual part, or one planned
//! run on a real part's measured map (`--map`).

use super::map_input::{print_input_notes, MapInputArgs};
use super::shop_tool_args::ShopToolArgs;
use super::tif_source::TifArgs;
use crate::progress::Bars;
use anyhow::{bail, Context};
use preston_io::calibration::read_calibration;
use preston_io::pipeline::{calibrated_tif_warning, is_spot_test_of};
use preston_io::readers::read_tif;
use preston_io::simulation::write_loop;
use preston_io::surface::read_surface;
use preston_solver::dwell::{FeedLimits, Settings};
use preston_solver::influence::model::surface::TifFrame;
use preston_solver::iterate::learned::next_run_rate_sigma;
use preston_solver::iterate::{band::BAND_MIN_GAIN, CorrectableBand, MIN_GAIN_NM};
use preston_solver::iterate::{
    plan_measured, run_virtual, Disturbances, FormErrorModel, LoopSettings, VirtualPart,
    LOOP_SOLVE_TOLERANCE,
};
use preston_solver::map::BoundingBox;
use preston_solver::registration::{
    RegisterSettings, INSTALLATION_RANGE_DEG, INSTALLATION_RANGE_MM,
};
use preston_solver::surface::{Plane, Surface};
use preston_solver::tif::Tif;
use std::path::PathBuf;

use super::EXIT_NOT_CONVERGED;

/// Arguments of `preston iterate`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Design surface JSON (default: the plane z = 0; use a surface whose shape fixes all six
    /// rigid-body motions for a meaningful registration).
    #[arg(long, value_name = "S.json")]
    pub surface: Option<PathBuf>,
    #[command(flatten)]
    pub tif: TifArgs,
    /// Real part: plan one run on this measured map (CSV `x_mm,y_mm,z_nm` or any format of
    /// `preston map convert`) instead of a virtual loop.
    #[arg(long, value_name = "FILE")]
    pub map: Option<PathBuf>,
    #[command(flatten)]
    pub map_input: MapInputArgs,
    /// Pixel pitch of a .npy map grid (or a 4D file without one), mm.
    #[arg(long, value_name = "MM")]
    pub map_pitch_mm: Option<f64>,
    /// Real part: the loop iteration this run is (chooses the intersection path's direction
    /// and shift).
    #[arg(long, default_value_t = 0)]
    pub iteration: usize,
    /// Aperture x range, mm (virtual part).
    #[arg(long, value_delimiter = ',', default_values_t = [-25.0, 25.0], allow_hyphen_values = true)]
    pub aperture_x_mm: Vec<f64>,
    /// Aperture y range, mm (virtual part).
    #[arg(long, value_delimiter = ',', default_values_t = [-25.0, 25.0], allow_hyphen_values = true)]
    pub aperture_y_mm: Vec<f64>,
    /// Measurement grid points along x and y (virtual part).
    #[arg(long, value_delimiter = ',', default_values_t = [51, 51])]
    pub grid: Vec<usize>,
    /// Pitch of the intersection raster, mm.
    #[arg(long, default_value_t = 1.0)]
    pub pitch_mm: f64,
    /// Raster extension past the aperture, mm (default: the TIF radius).
    #[arg(long)]
    pub margin_mm: Option<f64>,
    /// Fastest feed, mm/min.
    #[arg(long = "v-max", default_value_t = 3000.0)]
    pub v_max_mm_per_min: f64,
    /// Slowest feed, mm/min (0 = none).
    #[arg(long = "v-min", default_value_t = 0.0)]
    pub v_min_mm_per_min: f64,
    /// Weight of total dwell time in each run's objective, nm^2 per s.
    #[arg(long, default_value_t = 0.01)]
    pub rho: f64,
    /// Weight of dwell-time differences along the path, nm^2/s^2.
    #[arg(long, default_value_t = 0.0)]
    pub lambda: f64,
    /// Relative optimality tolerance of each run's dwell solve, for either solver (the TIF rate
    /// error of a real run, per cent, dwarfs it).
    #[arg(long, default_value_t = LOOP_SOLVE_TOLERANCE)]
    pub tolerance: f64,
    /// Dwell solver: qp, first-order or auto (by size: first-order from 5,000 dwell points).
    #[arg(long, value_enum, default_value = "auto")]
    pub solver: preston_solver::dwell::SolverChoice,
    /// Polishing runs at most.
    #[arg(long, default_value_t = 5)]
    pub iterations: usize,
    /// Stop when the measured RMS is at or below this, nm.
    #[arg(long, default_value_t = 0.0)]
    pub spec_rms_nm: f64,
    /// Stop when the measured PV is at or below this, nm.
    #[arg(long, default_value_t = 0.0)]
    pub spec_pv_nm: f64,
    /// Virtual part: RMS of the generated form error, nm.
    #[arg(long, default_value_t = 100.0)]
    pub form_error_rms_nm: f64,
    /// Virtual part: highest spatial frequency of the form error, cycles across the aperture.
    #[arg(long, default_value_t = 2.0)]
    pub form_error_cycles: f64,
    /// Virtual part: seed of the form error.
    #[arg(long, default_value_t = 1)]
    pub form_error_seed: u64,
    /// Virtual part: installation rotation vector, arcsec.
    #[arg(long, value_delimiter = ',', default_values_t = [0.0, 0.0, 0.0], allow_hyphen_values = true)]
    pub rotation_arcsec: Vec<f64>,
    /// Virtual part: installation translation, um.
    #[arg(long, value_delimiter = ',', default_values_t = [0.0, 0.0, 0.0], allow_hyphen_values = true)]
    pub translation_um: Vec<f64>,
    /// Virtual part: measurement noise (standard deviation along z), nm.
    #[arg(long, default_value_t = 0.0)]
    pub noise_nm: f64,
    /// Largest relative TIF rate error of a run (0.03 = 3%).
    #[arg(long, default_value_t = 0.0)]
    pub tif_rate_error: f64,
    /// Standard deviation of the dwell-position error per axis, mm.
    #[arg(long, default_value_t = 0.0)]
    pub positioning_noise_mm: f64,
    #[command(flatten)]
    pub tool: ShopToolArgs,
    /// Virtual part: relative standard deviation of each run's step of the tool rate's random
    /// walk (the rate wanders from run to run).
    #[arg(long, default_value_t = 0.0)]
    pub rate_walk_per_run: f64,
    /// Virtual part: learn the whole tool from each run (its measured removal calibrated for
    /// rate, width, offset, shape and drift, as `preston calibrate` does) instead of its rate
    /// alone; flat parts only.
    #[arg(long)]
    pub calibrate: bool,
    /// Real part: plan with this calibration (`preston calibrate`'s calibration.json): its
    /// calibrated TIF (unless --tif names one), its rate's uncertainty and its drift.
    #[arg(
        long,
        value_name = "calibration.json",
        requires = "map",
        conflicts_with = "rate_factor"
    )]
    pub calibration: Option<PathBuf>,
    /// Seed of the noise generators.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Registration: range of the installation error's translations, mm (a motion whose
    /// standard deviation exceeds it is held; see `preston register`).
    #[arg(long, value_name = "MM", default_value_t = INSTALLATION_RANGE_MM)]
    pub installation_range_mm: f64,
    /// Registration: range of the installation error's rotations, degrees.
    #[arg(long, value_name = "DEG", default_value_t = INSTALLATION_RANGE_DEG)]
    pub installation_range_deg: f64,
    /// Plan against the whole measured map instead of its correctable band (the smooth part up
    /// to where the TIF's transfer function falls to --band-gain).
    #[arg(long)]
    pub no_band: bool,
    /// Transfer-function gain of the TIF at the cap of the correctable band, in (0, 1); within
    /// it the data choose the band (Bayesian information criterion).
    #[arg(long, value_name = "G", default_value_t = BAND_MIN_GAIN)]
    pub band_gain: f64,
    /// Rate factor of the first run (a rate learned on earlier parts), times the TIF's rate.
    #[arg(long, default_value_t = 1.0)]
    pub rate_factor: f64,
    /// Stop when the next run is predicted to lower the measured RMS by less than this, nm.
    #[arg(long, default_value_t = MIN_GAIN_NM)]
    pub min_gain_nm: f64,
    /// Write the figures (also embedded in report.html, written every run) next to the CSVs.
    #[arg(long)]
    pub plots: bool,
    #[command(flatten)]
    pub figures: super::figure_args::FigureArgs,
    /// Output directory.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
}

fn pair<T: Copy>(v: &[T], what: &str) -> anyhow::Result<[T; 2]> {
    match v {
        [a, b] => Ok([*a, *b]),
        _ => bail!("--{what} takes two values A,B"),
    }
}

fn triple(v: &[f64], what: &str) -> anyhow::Result<[f64; 3]> {
    match v {
        [a, b, c] => Ok([*a, *b, *c]),
        _ => bail!("--{what} takes three values A,B,C"),
    }
}

/// Runs `preston iterate`.
pub fn run(args: Args) -> anyhow::Result<u8> {
    let calibration = args
        .calibration
        .as_deref()
        .map(read_calibration)
        .transpose()?;
    let tif = match &calibration {
        Some(c)
            if !args.tif.given()
                || is_spot_test_of(c, args.tif.tif.first().map(|p| p.as_path())) =>
        {
            Tif::Grid(read_tif(&c.tif_file)?)
        }
        _ => args.tif.load()?,
    };
    if let Some(w) = calibration
        .as_ref()
        .and_then(|c| calibrated_tif_warning(c, &tif))
    {
        crate::errln!("  warning: {w}");
    }
    if let Some(c) = &calibration {
        crate::note!(
            "  calibrated tool: rate {:.4} +- {:.4}, width {:.4}, offset ({:+.4}, {:+.4}) mm, drift {:+.4} per hour (the TIF {})",
            c.rate_factor,
            c.rate_factor_sigma,
            c.width_factor,
            c.offset_x_mm,
            c.offset_y_mm,
            c.drift_per_hour,
            c.tif_file.display()
        );
    }
    let surface = match &args.surface {
        Some(p) => read_surface(p)?,
        None => Surface::Plane(Plane {}),
    };
    let [x0, x1] = pair(&args.aperture_x_mm, "aperture-x-mm")?;
    let [y0, y1] = pair(&args.aperture_y_mm, "aperture-y-mm")?;
    let settings = LoopSettings {
        aperture: BoundingBox {
            x_min_mm: x0,
            x_max_mm: x1,
            y_min_mm: y0,
            y_max_mm: y1,
        },
        grid: pair(&args.grid, "grid")?,
        path_pitch_mm: args.pitch_mm,
        path_margin_mm: args.margin_mm,
        feed: FeedLimits {
            v_max_mm_per_min: args.v_max_mm_per_min,
            v_min_mm_per_min: args.v_min_mm_per_min,
        },
        max_iterations: args.iterations,
        spec_rms_nm: args.spec_rms_nm,
        spec_pv_nm: args.spec_pv_nm,
        rho: args.rho,
        lambda: args.lambda,
        disturbances: Disturbances {
            tif_rate_error: args.tif_rate_error,
            positioning_noise_mm: args.positioning_noise_mm,
            tool: args.tool.tool()?,
            rate_walk_per_run: args.rate_walk_per_run,
        },
        calibrate: args.calibrate,
        // A spot test and a calibration state the footprint in the machine's axes.
        tif_frame: if args.calibrate || calibration.is_some() {
            TifFrame::MachineX
        } else {
            TifFrame::PathTangent
        },
        drift_per_hour: calibration.as_ref().map_or(0.0, |c| c.drift_per_hour),
        seed: args.seed,
        band: if args.no_band {
            CorrectableBand::All
        } else {
            CorrectableBand::Tif {
                min_gain: args.band_gain,
            }
        },
        rate_factor: if calibration.is_some() {
            1.0
        } else {
            args.rate_factor
        },
        min_gain_nm: args.min_gain_nm,
        rate_uncertainty: calibration
            .as_ref()
            .map_or(LoopSettings::default().rate_uncertainty, |c| {
                next_run_rate_sigma(c.rate_factor, c.rate_factor_sigma)
            }),
        register: RegisterSettings {
            installation_range_mm: args.installation_range_mm,
            installation_range_deg: args.installation_range_deg,
            ..RegisterSettings::default()
        },
        solver: Settings {
            tolerance: args.tolerance,
            first_order_tolerance: args.tolerance,
            solver: args.solver,
            ..Settings::default()
        },
        ..LoopSettings::default()
    };
    settings.validate()?;
    let bars = Bars::new();
    let outcome = match &args.map {
        Some(m) => {
            let map = args.map_input.source(m.clone(), args.map_pitch_mm).read()?;
            print_input_notes(&map.input);
            plan_measured(&surface, &map.map, &tif, &settings, args.iteration, &bars)
                .with_context(|| format!("planning a run on {}", m.display()))?
        }
        None => {
            let part = VirtualPart {
                surface,
                form_error: FormErrorModel {
                    rms_nm: args.form_error_rms_nm,
                    max_cycles: args.form_error_cycles,
                    seed: args.form_error_seed,
                    ..FormErrorModel::default()
                },
                rotation_arcsec: triple(&args.rotation_arcsec, "rotation-arcsec")?,
                translation_um: triple(&args.translation_um, "translation-um")?,
                measurement_noise_nm: args.noise_nm,
            };
            run_virtual(&part, &tif, &settings, &bars)?
        }
    };
    write_loop(&outcome, &args.out, args.plots, args.figures.style())
        .with_context(|| format!("writing outputs to {}", args.out.display()))?;
    crate::note!(
        "iteration,pv_nm,rms_nm,max_abs_nm,mean_abs_nm,time_s,predicted_rms_nm,\
         rate_factor_estimate,uncorrectable_rms_nm"
    );
    let opt = |v: Option<f64>| v.map(|v| format!("{v:.3}")).unwrap_or_default();
    for r in &outcome.records {
        crate::note!(
            "{},{:.3},{:.3},{:.3},{:.3},{:.2},{},{},{}",
            r.iteration,
            r.pv_nm,
            r.rms_nm,
            r.max_abs_nm,
            r.mean_abs_nm,
            r.time_s,
            opt(r.predicted_rms_nm),
            opt(r.rate_factor_estimate),
            opt(r.uncorrectable_rms_nm)
        );
    }
    if let Some(floor) = outcome
        .records
        .iter()
        .rev()
        .find_map(|r| r.uncorrectable_rms_nm)
    {
        crate::note!(
            "  floor: {floor:.3} nm RMS of the measured error is outside the TIF's correctable \
             band (measurement noise and finer structure)"
        );
    }
    crate::note!(
        "preston iterate: stopped because {}; spec {}; wrote {}",
        outcome.stop.describe(),
        if outcome.met_spec { "met" } else { "not met" },
        args.out.display()
    );
    if !outcome.not_converged.is_empty() {
        for f in &outcome.not_converged {
            crate::errln!(
                "  warning: iteration {}: the {} did not converge ({})",
                f.iteration,
                f.step.name(),
                f.detail
            );
        }
        return Ok(EXIT_NOT_CONVERGED);
    }
    Ok(crate::EXIT_OK)
}
