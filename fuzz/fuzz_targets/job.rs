//! Arbitrary UTF-8 into the job-file parser (`preston_io::job::Job::parse`). Errors are fine; a
//! panic is a bug. An accepted job must survive a TOML round trip: serialising it must succeed,
//! the text must parse back, the second serialisation must equal the first, and the re-parsed job
//! must equal the original (compared only when the job equals itself, i.e. holds no NaN).
#![no_main]

use libfuzzer_sys::fuzz_target;
use preston_io::job::Job;
use std::path::Path;

fuzz_target!(|text: &str| {
    let Ok(job) = Job::parse(text, Path::new("fuzz.toml")) else {
        return;
    };
    let s1 = toml::to_string(&job).expect("an accepted job serialises to TOML");
    let again = match Job::parse(&s1, Path::new("fuzz-roundtrip.toml")) {
        Ok(j) => j,
        Err(e) => panic!("serialised job does not parse back: {e}\n--- serialised ---\n{s1}"),
    };
    let s2 = toml::to_string(&again).expect("re-parsed job serialises");
    assert_eq!(s1, s2, "TOML round trip is not stable");
    #[allow(clippy::eq_op)]
    let nan_free = job == job;
    if nan_free {
        assert_eq!(job, again, "TOML round trip changed the job");
    }
});
