//! Process-wide counts of the steps that run once per job: reading the job file and validating
//! the solver settings. They cost one relaxed atomic increment each and let a test of the whole
//! binary check that a command does each step once (`preston` prints them on stderr at exit when
//! the environment variable `PRESTON_DEBUG_COUNTS` is set).

use std::sync::atomic::{AtomicUsize, Ordering};

/// A step counted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Counted {
    /// A job file's text parsed (`preston_io::job::Job::parse`).
    JobParsed,
    /// The dwell solver settings validated ([`crate::dwell::Settings::validate`]).
    SettingsValidated,
    /// The job's choices validated ([`crate::setup::Choices::check`]).
    ChoicesChecked,
}

impl Counted {
    /// Every counted step, in the order [`counts`] gives them.
    pub const ALL: [Counted; 3] = [
        Counted::JobParsed,
        Counted::SettingsValidated,
        Counted::ChoicesChecked,
    ];

    /// The step's name in the printed counts.
    pub fn name(self) -> &'static str {
        match self {
            Counted::JobParsed => "job_parsed",
            Counted::SettingsValidated => "settings_validated",
            Counted::ChoicesChecked => "choices_checked",
        }
    }
}

static COUNTS: [AtomicUsize; 3] = [
    AtomicUsize::new(0),
    AtomicUsize::new(0),
    AtomicUsize::new(0),
];

/// Counts one `step`.
pub fn record(step: Counted) {
    COUNTS[step as usize].fetch_add(1, Ordering::Relaxed);
}

/// How often each step of [`Counted::ALL`] ran in this process.
pub fn counts() -> [(Counted, usize); 3] {
    Counted::ALL.map(|c| (c, COUNTS[c as usize].load(Ordering::Relaxed)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_recorded_step_is_counted_once_per_call() {
        let before = counts()[1].1;
        record(Counted::SettingsValidated);
        record(Counted::SettingsValidated);
        // Other tests of this process may validate settings meanwhile: at least two more.
        assert!(counts()[1].1 >= before + 2);
        assert_eq!(counts()[1].0, Counted::SettingsValidated);
    }
}
