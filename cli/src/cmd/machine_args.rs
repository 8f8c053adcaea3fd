//! The machine on the command line: its feed and acceleration limits, corner angle and
//! controller, one definition flattened into `solve`, `nc` and `simulate`, turned into the
//! job's `[machine]` and `[nc]` keys in one place ([`MachineArgs::apply`]).

use anyhow::bail;
use preston_io::job::Job;
use preston_io::overrides::{Overrides, COMMAND_LINE};
use preston_solver::machine::gcode::dialect::{Dialect, FeedMode};
use preston_solver::machine::profile::WorkOffset;
use std::path::Path;

/// The machine's flags (each over the job's and the machine profile's key).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct MachineArgs {
    /// Fastest feed, mm/min (default: the job's [machine] v_max_mm_per_min). solve: the plan's
    /// feed limit; with several tools once for all, or once per tool in order. nc: a stretch
    /// whose tool-centre move needs more is programmed at v_max and reported. simulate: reports
    /// bound violations of the plan (optional; the job's is not used).
    #[arg(
        long = "v-max",
        value_name = "MM_PER_MIN",
        allow_negative_numbers = true,
        action = clap::ArgAction::Append
    )]
    pub v_max_mm_per_min: Vec<f64>,
    /// Acceleration limit along each path line, mm/s^2 (default: the job's). solve: the plan
    /// keeps |v_{j+1}^2 - v_j^2| <= 2 a s_j, s_j the distance between consecutive dwell points;
    /// nc: the program is also executed with this limit and the stretch times reported;
    /// simulate --program: the controller's path acceleration (trapezoidal look-ahead; none:
    /// every block at its programmed feed).
    #[arg(long, value_name = "MM_PER_S2", allow_negative_numbers = true)]
    pub a_max_mm_per_s2: Option<f64>,
    /// Turn angle (degrees) above which the path splits into lines and the machine stops at a
    /// corner, for the acceleration limit and the machining time (default 60); the job's
    /// [machine] corner_angle_deg where the flag is not given.
    #[arg(long, value_name = "DEG", allow_negative_numbers = true)]
    pub corner_angle_deg: Option<f64>,
    /// Controller dialect (default: the machine profile's, else iso; simulate --program: else
    /// the one its header names).
    #[arg(long, value_enum)]
    pub dialect: Option<Dialect>,
    /// `per-minute` (G94, F in mm/min) or `inverse-time` (G93, F = 1 / block minutes) (default:
    /// the machine profile's, else per-minute).
    #[arg(long, value_enum)]
    pub feed_mode: Option<FeedMode>,
    /// Work offset selected at the start (default: the machine profile's, else g54).
    #[arg(long, value_enum)]
    pub work_offset: Option<WorkOffset>,
}

impl MachineArgs {
    /// The flags given over the job's `[machine]` (the feed limit where one is given, the
    /// acceleration limit, the corner angle: through [`Overrides::apply`], which checks each
    /// value naming its flag) and `[nc]` (dialect, feed mode, work offset): the one place they
    /// become job keys. Repeated `--v-max` (several tools in `solve`) is left to the caller.
    pub fn apply(&self, job: &mut Job) -> anyhow::Result<()> {
        Overrides {
            v_max_mm_per_min: match self.v_max_mm_per_min.as_slice() {
                [v] => Some(*v),
                _ => None,
            },
            a_max_mm_per_s2: self.a_max_mm_per_s2,
            corner_angle_deg: self.corner_angle_deg,
            ..Overrides::default()
        }
        .apply(job, Path::new(COMMAND_LINE))?;
        if let Some(d) = self.dialect {
            job.nc.dialect = d;
        }
        if let Some(f) = self.feed_mode {
            job.nc.feed_mode = f;
        }
        if let Some(w) = self.work_offset {
            job.nc.work_offset = w;
        }
        Ok(())
    }

    /// The one feed limit given (none: not given); repeated only for several tools.
    pub fn v_max_mm_per_min(&self) -> anyhow::Result<Option<f64>> {
        match self.v_max_mm_per_min.as_slice() {
            [] => Ok(None),
            [v] => Ok(Some(*v)),
            _ => bail!(
                "--v-max is repeated only with several tools (solve's repeated --tif and --dwell)"
            ),
        }
    }
}
