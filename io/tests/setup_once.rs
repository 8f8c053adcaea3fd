//! One job through the pipeline as `preston solve --job data/job.toml` runs it: the job's
//! choices are validated once, the inputs resolved once, the problem built once, and the removal
//! `R t` and the feed schedule of the solution computed once each (counted by an observer).

use preston_io::job::Job;
use preston_io::pipeline;
use preston_solver::observer::{Observer, SetupStep};
use std::path::Path;
use std::sync::Mutex;

#[derive(Default)]
struct Counting(Mutex<Vec<SetupStep>>);

impl Observer for Counting {
    fn setup_step(&self, step: SetupStep) {
        if let Ok(mut v) = self.0.lock() {
            v.push(step);
        }
    }
}

#[test]
fn the_sample_job_is_resolved_once_and_its_removal_and_feeds_computed_once() {
    let job_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/job_point_1mm.toml");
    let job = Job::load(&job_path).unwrap();
    let counting = Counting::default();
    let prepared = pipeline::prepare(&job, &job_path, &counting).unwrap();
    let solved = pipeline::solve(prepared, &job, &counting).unwrap();
    let out = std::env::temp_dir().join(format!("preston-setup-once-{}", std::process::id()));
    pipeline::write_outputs(&solved, &out).unwrap();
    let _ = std::fs::remove_dir_all(&out);
    let steps = counting.0.into_inner().unwrap();
    assert_eq!(
        steps,
        vec![
            SetupStep::CheckChoices,
            SetupStep::Resolve,
            SetupStep::BuildProblem,
            SetupStep::Solve,
            SetupStep::Removal,
            SetupStep::FeedSchedule,
        ]
    );
    // The outcome's model removal is R t on the measured map, computed once; the headline's
    // (report and files) is the executed program's, this job having an acceleration limit.
    let removal = solved
        .prepared
        .problem
        .removal_nm(&solved.solution().dwell_s)
        .unwrap();
    assert_eq!(
        &removal[..solved.prepared.map().len()],
        &solved.outcome.removal_nm[..]
    );
    let executed = preston_io::residual::executed_removal_nm(&solved.outcome);
    assert_eq!(executed, Some(solved.removal_nm()));
}
