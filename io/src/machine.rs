//! Files of the machine commands (`preston nc`, `preston asphere`): the solved dwell file as NC
//! input, measured profile errors, the job-file `[nc]` table, and the staged G-code, point list
//! and asphere programs. Column names carry units and are a contract.

use crate::atomic::{stage, Staged};
use crate::error::{Error, Result};
use crate::table::{read_table, ColumnSpec};
use preston_solver::machine::asphere::{write_nc, AsphereJob, AsphereLine, ProfileError};
use preston_solver::machine::gcode::ProgramCheck;
use preston_solver::machine::nc::NcProgram;
use preston_solver::path::DwellPath;
use std::path::Path;

/// A solved dwell file: the path and a dwell time per point.
#[derive(Debug, Clone, PartialEq)]
pub struct DwellTimes {
    /// The points in path order.
    pub path: DwellPath,
    /// Dwell time per point, s.
    pub dwell_s: Vec<f64>,
}

/// Reads the `dwell.csv` that `preston solve` writes (`x_mm,y_mm,ds_mm,dwell_s,feed_mm_per_min`;
/// only `x_mm`, `y_mm` and `dwell_s` are used, `ds_mm` and the feed are recomputed from the
/// points). `dwell_s` is required and must be non-negative; at least one row.
pub fn read_dwell_times(path: &Path) -> Result<DwellTimes> {
    let d = crate::readers::read_dwell_columns(path, ColumnSpec::required("dwell_s"))?;
    Ok(DwellTimes {
        path: d.path,
        dwell_s: d.dwell_s.unwrap_or_default(),
    })
}

/// Reads a measured radial profile error `x_mm,error_nm` (at least two rows, distinct `x_mm`).
pub fn read_profile_error(path: &Path) -> Result<ProfileError> {
    let mut t = read_table(
        path,
        &[
            ColumnSpec::required("x_mm"),
            ColumnSpec::required("error_nm"),
        ],
    )?;
    ProfileError::new(t.take(0).unwrap_or_default(), t.take(1).unwrap_or_default())
        .map_err(|e| Error::engine(path, e))
}

/// Stages the point list `x_mm,y_mm,z_mm,nx,ny,nz,dwell_s,feed_mm_per_min` of a program.
pub fn stage_points_csv(path: &Path, program: &NcProgram) -> Result<Staged> {
    stage(path, |w| program.write_points_csv(w))
}

/// Stages an asphere program (`N<k> X<x> Z<z> B<b> S<rpm> F<feed>` lines).
pub fn stage_asphere_nc(path: &Path, job: &AsphereJob, lines: &[AsphereLine]) -> Result<Staged> {
    stage(path, |w| write_nc(job, lines, w))
}

/// What the program as written does with the plan, as JSON (`--json`).
pub fn program_check_summary(check: &ProgramCheck) -> serde_json::Value {
    let w = &check.written;
    serde_json::json!({
        "machining_time_s": w.stretch_time_s + w.plunge_time_s,
        "stretch_time_s": w.stretch_time_s,
        "plunge_time_s": w.plunge_time_s,
        "feed_blocks": w.feed_blocks,
        "arc_blocks": w.arc_blocks,
        "merged_stretches": w.merged_stretches,
        "slowed_stretches": w.slowed_stretches,
        "programmed": check.programmed,
        "accelerated": check.accelerated,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn file(text: &str) -> tempfile::NamedTempFile {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(text.as_bytes()).unwrap();
        f
    }

    #[test]
    fn dwell_times_need_the_dwell_column() {
        let f = file("x_mm,y_mm,ds_mm,dwell_s,feed_mm_per_min\n0,0,1,0.5,120\n1,0,1,0.25,240\n");
        let d = read_dwell_times(f.path()).unwrap();
        assert_eq!(d.dwell_s, vec![0.5, 0.25]);
        assert_eq!(d.path.x_mm(), &[0.0, 1.0]);
        let f = file("x_mm,y_mm\n0,0\n");
        let e = read_dwell_times(f.path()).unwrap_err().to_string();
        assert!(e.contains("dwell_s"), "{e}");
        let f = file("x_mm,y_mm,dwell_s\n0,0,-1\n");
        let e = read_dwell_times(f.path()).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("negative"), "{e}");
    }

    #[test]
    fn profile_error_reads_and_validates() {
        let f = file("error_nm,x_mm\n5,1\n3,0\n");
        let p = read_profile_error(f.path()).unwrap();
        assert_eq!(p.x_mm(), &[0.0, 1.0]);
        assert_eq!(p.range_nm(), (3.0, 5.0));
        let f = file("x_mm,error_nm\n0,1\n");
        assert!(read_profile_error(f.path()).is_err());
    }
}
