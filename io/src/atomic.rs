//! Atomic output: write to a temporary file in the destination's directory, then rename it into
//! place, so a reader (or a crash) sees either the old file or the whole new one. Files are
//! created with the process umask, as `File::create` would (0644 under umask 022).
//!
//! A command stages every output (CSV, JSON, G-code and plots) before it renames any: a failure
//! while writing one of them leaves all previous outputs in place. The renames of one commit run
//! under a lock on each output directory (`.preston.lock`, created exclusively, holding the
//! process id), so two runs into one directory commit one after the other and the directory
//! ends up with one run's complete set, never a mix. A lock whose process is gone is taken over;
//! a live one is waited for up to [`DEFAULT_LOCK_WAIT_S`] seconds (`PRESTON_LOCK_WAIT_S`
//! overrides), then the commit fails naming the holder. Temporary files carry the writer's
//! process id (`.dwell.csv.preston-1234-XXXXXX.tmp`); those of processes that no longer run (a
//! run killed while writing) are removed at the next commit into their directory.

use crate::error::{Error, Result};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

/// Writes `path` atomically: `fill` writes the content into a buffered temporary file in the same
/// directory, which is flushed, synced and renamed over `path` only if `fill` succeeds.
pub fn write_atomic<F>(path: &Path, fill: F) -> Result<()>
where
    F: FnOnce(&mut dyn Write) -> std::io::Result<()>,
{
    let staged = stage(path, fill)?;
    commit_all(vec![staged])
}

/// A fully written temporary file waiting to be renamed into place.
#[derive(Debug)]
pub struct Staged {
    temp: tempfile::NamedTempFile,
    dest: PathBuf,
}

impl Staged {
    /// Where the file goes on commit.
    pub fn dest(&self) -> &Path {
        &self.dest
    }

    /// The staged content, read back from the temporary file.
    pub fn read_back(&self) -> Result<Vec<u8>> {
        std::fs::read(self.temp.path()).map_err(|e| Error::io(&self.dest, e))
    }

    /// Renames the temporary file over its destination.
    pub fn commit(self) -> Result<()> {
        let dest = self.dest;
        self.temp
            .persist(&dest)
            .map_err(|e| Error::io(&dest, e.error))?;
        Ok(())
    }
}

/// Writes the content into a temporary file next to `path` and returns it un-renamed, so several
/// outputs can be staged and committed together once all of them succeeded.
pub fn stage<F>(path: &Path, fill: F) -> Result<Staged>
where
    F: FnOnce(&mut dyn Write) -> std::io::Result<()>,
{
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "output".into());
    let prefix = temp_prefix(&name);
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix).suffix(".tmp");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        // Requested as 0666; the kernel applies the umask on creation.
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let temp = builder.tempfile_in(&dir).map_err(|e| Error::io(path, e))?;
    {
        let mut w = BufWriter::with_capacity(1 << 20, temp.as_file());
        fill(&mut w).map_err(|e| Error::io(path, e))?;
        w.flush().map_err(|e| Error::io(path, e))?;
    }
    temp.as_file().sync_all().map_err(|e| Error::io(path, e))?;
    Ok(Staged {
        temp,
        dest: path.to_path_buf(),
    })
}

/// The prefix of a temporary file for the output `name` written by this process.
pub(crate) fn temp_prefix(name: &str) -> String {
    format!(".{name}.{TEMP_TAG}{}-", std::process::id())
}

/// Marks Preston's temporary files: `.NAME.preston-PID-XXXXXX.tmp`.
const TEMP_TAG: &str = "preston-";
/// The lock file of an output directory.
pub const LOCK_FILE: &str = ".preston.lock";
/// How long a commit waits for another run's lock on its directory, s.
pub const DEFAULT_LOCK_WAIT_S: f64 = 60.0;

/// Commits staged files together: all were fully written and synced before any is renamed, and
/// the renames run under the lock of each output directory (see the module documentation).
pub fn commit_all(staged: Vec<Staged>) -> Result<()> {
    commit_then(staged, |_| Ok(()))
}

/// [`commit_all`], then, under the same lock, removes from `dir` the outputs of an earlier run
/// that this one does not write, so the directory holds this run's outputs only: the files whose
/// name `earlier_output` recognises (the names the run's command writes, nothing else), that no
/// staged file replaces and that are not one of `keep` (the run's own inputs, compared by their
/// canonical paths). Regular files and symbolic links only (a link is removed, not its target);
/// directories are left. Returns the paths removed.
pub fn commit_replacing(
    staged: Vec<Staged>,
    dir: &Path,
    earlier_output: &dyn Fn(&str) -> bool,
    keep: &[PathBuf],
) -> Result<Vec<PathBuf>> {
    // The lock of `dir` is taken even when nothing is staged there.
    let _lock = if staged.iter().any(|s| dir_of(&s.dest) == dir) {
        None
    } else {
        Some(DirLock::acquire(dir, lock_wait_s())?)
    };
    commit_then(staged, |written| {
        remove_earlier_outputs(dir, written, earlier_output, keep)
    })
}

/// Removes the files of `dir` that `earlier_output` recognises, none of `written` and none of
/// `keep` ([`commit_replacing`]).
fn remove_earlier_outputs(
    dir: &Path,
    written: &[PathBuf],
    earlier_output: &dyn Fn(&str) -> bool,
    keep: &[PathBuf],
) -> Result<Vec<PathBuf>> {
    let canonical = |p: &Path| std::fs::canonicalize(p).ok();
    let kept: Vec<PathBuf> = keep.iter().filter_map(|p| canonical(p)).collect();
    let written: Vec<&std::ffi::OsStr> = written
        .iter()
        .filter(|p| dir_of(p) == dir)
        .filter_map(|p| p.file_name())
        .collect();
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut removed = Vec::new();
    for e in entries {
        let e = e.map_err(|e| Error::io(dir, e))?;
        let name = e.file_name();
        let Some(text) = name.to_str() else { continue };
        if !earlier_output(text) || written.contains(&name.as_os_str()) {
            continue;
        }
        let path = e.path();
        let is_file = e.file_type().is_ok_and(|t| t.is_file() || t.is_symlink());
        if !is_file || canonical(&path).is_some_and(|c| kept.contains(&c)) {
            continue;
        }
        std::fs::remove_file(&path).map_err(|err| {
            Error::io(
                &path,
                std::io::Error::new(
                    err.kind(),
                    format!(
                        "an earlier run's output that this run does not write could not be \
                         removed ({err}); remove it, it does not belong to this run's outputs"
                    ),
                ),
            )
        })?;
        removed.push(path);
    }
    Ok(removed)
}

/// [`commit_all`], running `then` with the committed destinations before the locks are released.
fn commit_then<T>(staged: Vec<Staged>, then: impl FnOnce(&[PathBuf]) -> Result<T>) -> Result<T> {
    let mut dirs: Vec<PathBuf> = staged.iter().map(|s| dir_of(&s.dest)).collect();
    dirs.sort();
    dirs.dedup();
    let mut locks = Vec::with_capacity(dirs.len());
    for d in &dirs {
        locks.push(DirLock::acquire(d, lock_wait_s())?);
        remove_stale_temps(d);
    }
    // What would make a rename fail is checked before the first one.
    for s in &staged {
        if std::fs::symlink_metadata(&s.dest).is_ok_and(|m| m.is_dir()) {
            return Err(Error::io(
                &s.dest,
                std::io::Error::new(
                    std::io::ErrorKind::IsADirectory,
                    "is a directory; nothing was written",
                ),
            ));
        }
    }
    let written: Vec<PathBuf> = staged.iter().map(|s| s.dest.clone()).collect();
    for (done, s) in staged.into_iter().enumerate() {
        injected_kill(done);
        s.commit()?;
    }
    let out = then(&written);
    drop(locks);
    out
}

/// Test hook: with `PRESTON_KILL_AT_COMMIT=N` in the environment the process aborts (as a kill
/// would end it) when `N` files of a commit have been renamed into place: 0 is after every
/// output is staged and before the first rename. Lets tests inject the failure where they mean
/// it instead of hoping a timed kill lands there.
fn injected_kill(done: usize) {
    if let Some(n) = std::env::var_os("PRESTON_KILL_AT_COMMIT") {
        if n.to_str().and_then(|v| v.trim().parse::<usize>().ok()) == Some(done) {
            std::process::abort();
        }
    }
}

fn dir_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

fn lock_wait_s() -> f64 {
    std::env::var("PRESTON_LOCK_WAIT_S")
        .ok()
        .and_then(|v| v.trim().parse::<f64>().ok())
        .filter(|v| v.is_finite() && *v >= 0.0)
        .unwrap_or(DEFAULT_LOCK_WAIT_S)
}

/// Whether process `pid` runs (Linux: `/proc/PID`; elsewhere every process counts as running,
/// so nothing is taken over or removed).
fn pid_alive(pid: u32) -> bool {
    if pid == std::process::id() {
        return true;
    }
    if cfg!(target_os = "linux") {
        Path::new(&format!("/proc/{pid}")).exists()
    } else {
        true
    }
}

/// The lock on an output directory, released (its file removed) when dropped.
#[derive(Debug)]
pub struct DirLock {
    file: PathBuf,
}

impl DirLock {
    /// Takes the lock of `dir`, taking over one whose process is gone and waiting up to
    /// `wait_s` seconds for a live one.
    pub fn acquire(dir: &Path, wait_s: f64) -> Result<Self> {
        let file = dir.join(LOCK_FILE);
        let began = std::time::Instant::now();
        loop {
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&file)
            {
                Ok(mut f) => {
                    // The pid is informative; the lock is the file's existence.
                    let _ = writeln!(f, "{}", std::process::id());
                    return Ok(Self { file });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(Error::io(&file, e)),
            }
            let holder = std::fs::read_to_string(&file)
                .ok()
                .and_then(|t| t.trim().parse::<u32>().ok());
            match holder {
                Some(pid) if !pid_alive(pid) => {
                    // Left by a run that was killed: take it over.
                    let _ = std::fs::remove_file(&file);
                    continue;
                }
                None if age_s(&file) > 10.0 => {
                    // Unreadable and not being written: left by a run killed while creating it.
                    let _ = std::fs::remove_file(&file);
                    continue;
                }
                _ => {}
            }
            if began.elapsed().as_secs_f64() >= wait_s {
                let who =
                    holder.map_or_else(|| "another run".to_string(), |p| format!("process {p}"));
                return Err(Error::io(
                    &file,
                    std::io::Error::new(
                        std::io::ErrorKind::WouldBlock,
                        format!(
                            "{who} is writing into {} (waited {wait_s} s); run one command per \
                             output directory at a time, or remove the lock file if no such run exists",
                            dir.display()
                        ),
                    ),
                ));
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }
}

impl Drop for DirLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.file);
    }
}

fn age_s(path: &Path) -> f64 {
    std::fs::metadata(path)
        .and_then(|m| m.modified())
        .ok()
        .and_then(|t| t.elapsed().ok())
        .map_or(0.0, |d| d.as_secs_f64())
}

/// The writer's pid of a Preston temporary file name (`.NAME.preston-PID-XXXXXX.tmp|.png`).
fn temp_pid(name: &str) -> Option<u32> {
    if !name.starts_with('.') || !(name.ends_with(".tmp") || name.ends_with(".png")) {
        return None;
    }
    let at = name.rfind(TEMP_TAG)? + TEMP_TAG.len();
    let rest = &name[at..];
    let end = rest.find('-')?;
    rest[..end].parse().ok()
}

/// Removes the temporary files in `dir` left by Preston processes that no longer run. Best
/// effort: a file that cannot be removed stays.
pub fn remove_stale_temps(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut removed = 0;
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().to_string();
        if let Some(pid) = temp_pid(&name) {
            if !pid_alive(pid)
                && e.file_type().is_ok_and(|t| t.is_file())
                && std::fs::remove_file(e.path()).is_ok()
            {
                removed += 1;
            }
        }
    }
    removed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn failed_write_leaves_old_file_and_no_temp() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.csv");
        write_atomic(&p, |w| w.write_all(b"old\n")).unwrap();
        let r = write_atomic(&p, |w| {
            w.write_all(b"partial")?;
            Err(std::io::Error::other("boom"))
        });
        assert!(r.is_err());
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "old\n");
        let entries: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(entries.len(), 1, "temporary file left behind");
    }

    /// A pid no process has (beyond Linux's pid_max, 2^22).
    const DEAD_PID: u32 = 4_194_305;

    #[test]
    fn temp_names_carry_the_pid() {
        assert_eq!(temp_pid(".dwell.csv.preston-1234-abcDEF.tmp"), Some(1234));
        assert_eq!(temp_pid(".residual.png.preston-77-x1.png"), Some(77));
        assert_eq!(temp_pid("dwell.csv"), None);
        assert_eq!(temp_pid(".dwell.csv.abc.tmp"), None);
        assert!(temp_prefix("a.csv").starts_with(".a.csv.preston-"));
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn stale_temps_and_locks_of_dead_processes_are_cleared_live_ones_kept() {
        let dir = tempfile::tempdir().unwrap();
        let dead = dir
            .path()
            .join(format!(".dwell.csv.preston-{DEAD_PID}-abc.tmp"));
        let live = dir
            .path()
            .join(format!(".dwell.csv.preston-{}-abc.tmp", std::process::id()));
        std::fs::write(&dead, "partial").unwrap();
        std::fs::write(&live, "staging").unwrap();
        std::fs::write(dir.path().join(LOCK_FILE), format!("{DEAD_PID}\n")).unwrap();
        let p = dir.path().join("dwell.csv");
        write_atomic(&p, |w| w.write_all(b"new\n")).unwrap();
        assert_eq!(std::fs::read_to_string(&p).unwrap(), "new\n");
        assert!(!dead.exists() && live.exists());
        assert!(!dir.path().join(LOCK_FILE).exists(), "lock not released");
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_live_lock_is_waited_for_then_refused_naming_its_holder() {
        let dir = tempfile::tempdir().unwrap();
        let mut holder = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        std::fs::write(dir.path().join(LOCK_FILE), format!("{}\n", holder.id())).unwrap();
        let t0 = std::time::Instant::now();
        let e = DirLock::acquire(dir.path(), 0.2).unwrap_err().to_string();
        assert!(t0.elapsed().as_secs_f64() >= 0.2);
        assert!(e.contains(&format!("process {}", holder.id())), "{e}");
        holder.kill().unwrap();
        holder.wait().unwrap();
        // Its process gone, the lock is taken over at once.
        let lock = DirLock::acquire(dir.path(), 0.0).unwrap();
        drop(lock);
        assert!(!dir.path().join(LOCK_FILE).exists());
    }

    #[test]
    fn a_run_replaces_the_earlier_runs_outputs_and_nothing_else() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        for name in ["a.csv", "old.png", "input.png", "notes.txt"] {
            std::fs::write(d.join(name), "earlier").unwrap();
        }
        std::fs::create_dir(d.join("dir.png")).unwrap();
        let ours = |n: &str| n == "a.csv" || n.ends_with(".png");
        let staged = vec![stage(&d.join("a.csv"), |w| w.write_all(b"new\n")).unwrap()];
        let removed = commit_replacing(staged, d, &ours, &[d.join("input.png")]).unwrap();
        assert_eq!(removed, vec![d.join("old.png")]);
        assert_eq!(std::fs::read_to_string(d.join("a.csv")).unwrap(), "new\n");
        assert!(!d.join("old.png").exists());
        // The run's input, a file of another name and a directory stay.
        assert!(d.join("input.png").exists() && d.join("notes.txt").exists());
        assert!(d.join("dir.png").is_dir());
        assert!(!d.join(LOCK_FILE).exists(), "lock not released");
    }

    #[cfg(unix)]
    #[test]
    fn outputs_get_the_umask_mode_of_a_plain_create() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let plain = dir.path().join("plain.txt");
        std::fs::File::create(&plain).unwrap();
        let p = dir.path().join("a.csv");
        write_atomic(&p, |w| w.write_all(b"x\n")).unwrap();
        let mode = |q: &Path| std::fs::metadata(q).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&p), mode(&plain));
    }
}
