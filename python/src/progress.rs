//! The engine's progress reported to a Python callback (`progress=` of `preston.solve`), the
//! interpreter taken only for the call.

use crate::*;
use preston_solver::observer::SetupStep;
use std::sync::atomic::AtomicBool;

/// Forwards the engine's progress to a Python callable, at most about once per percent of a
/// stage and once per solver iteration. An exception raised by the callable is kept (the first
/// one) and raised when the work returns; later calls are skipped, and the engine is asked to
/// stop ([`Observer::cancelled`]).
pub(crate) struct PyProgress {
    callback: Py<PyAny>,
    error: Mutex<Option<PyErr>>,
    total: [AtomicU64; 3],
    done: [AtomicU64; 3],
    reported: [AtomicU64; 3],
}

pub(crate) fn stage_index(s: Stage) -> usize {
    match s {
        Stage::Assembly => 0,
        Stage::Solve => 1,
        Stage::Loop => 2,
    }
}

pub(crate) fn stage_name(s: Stage) -> &'static str {
    match s {
        Stage::Assembly => "assembly",
        Stage::Solve => "solve",
        Stage::Loop => "loop",
    }
}

impl PyProgress {
    pub(crate) fn new(callback: Py<PyAny>) -> Self {
        Self {
            callback,
            error: Mutex::new(None),
            total: Default::default(),
            done: Default::default(),
            reported: Default::default(),
        }
    }

    fn failed(&self) -> bool {
        self.error.lock().map_or(true, |e| e.is_some())
    }

    fn send(&self, stage: Stage, event: &str, info: Option<&IterationInfo>) {
        if self.failed() {
            return;
        }
        let i = stage_index(stage);
        let result = Python::attach(|py| -> PyResult<()> {
            let d = PyDict::new(py);
            d.set_item("stage", stage_name(stage))?;
            d.set_item("event", event)?;
            d.set_item("done", self.done[i].load(Ordering::Relaxed))?;
            d.set_item("total", self.total[i].load(Ordering::Relaxed))?;
            if let Some(info) = info {
                d.set_item("iteration", info.iteration)?;
                d.set_item("objective", info.objective)?;
                d.set_item("kkt_residual", info.kkt_residual)?;
            }
            self.callback.call1(py, (d,))?;
            Ok(())
        });
        if let Err(e) = result {
            if let Ok(mut slot) = self.error.lock() {
                slot.get_or_insert(e);
            }
        }
    }

    pub(crate) fn take_error(&self) -> Option<PyErr> {
        self.error.lock().ok().and_then(|mut e| e.take())
    }
}

impl Observer for PyProgress {
    fn start(&self, stage: Stage, total: u64) {
        let i = stage_index(stage);
        self.total[i].store(total, Ordering::Relaxed);
        self.done[i].store(0, Ordering::Relaxed);
        self.reported[i].store(0, Ordering::Relaxed);
        self.send(stage, "start", None);
    }

    fn advance(&self, stage: Stage, units: u64) {
        let i = stage_index(stage);
        let done = self.done[i].fetch_add(units, Ordering::Relaxed) + units;
        let step = (self.total[i].load(Ordering::Relaxed) / 100).max(1);
        let last = self.reported[i].load(Ordering::Relaxed);
        if done >= last + step
            && self.reported[i]
                .compare_exchange(last, done, Ordering::Relaxed, Ordering::Relaxed)
                .is_ok()
        {
            self.send(stage, "advance", None);
        }
    }

    fn finish(&self, stage: Stage) {
        self.send(stage, "finish", None);
    }

    fn iteration(&self, info: &IterationInfo) {
        self.send(Stage::Solve, "iteration", Some(info));
    }

    fn cancelled(&self) -> bool {
        self.failed()
    }
}

/// How often the interpreter is asked for pending signals while long work runs, ms.
const SIGNAL_CHECK_MS: u64 = 50;

/// Forwards to `inner` and reports the flag `cancel` as [`Observer::cancelled`].
struct Cancellable<'a> {
    inner: &'a dyn Observer,
    cancel: &'a AtomicBool,
}

impl Observer for Cancellable<'_> {
    fn start(&self, stage: Stage, total: u64) {
        self.inner.start(stage, total);
    }
    fn advance(&self, stage: Stage, units: u64) {
        self.inner.advance(stage, units);
    }
    fn finish(&self, stage: Stage) {
        self.inner.finish(stage);
    }
    fn iteration(&self, info: &IterationInfo) {
        self.inner.iteration(info);
    }
    fn setup_step(&self, step: SetupStep) {
        self.inner.setup_step(step);
    }
    fn cancelled(&self) -> bool {
        self.cancel.load(Ordering::Relaxed) || self.inner.cancelled()
    }
}

/// Runs `work` with the interpreter released, on a thread of its own, and gives it an observer
/// that forwards to `progress` (or ignores the progress) and asks the engine to stop once a
/// signal handler raised: this thread meanwhile asks the interpreter for pending signals every
/// [`SIGNAL_CHECK_MS`] (only the main thread's interpreter runs Python's signal handlers, and the
/// engine's own threads wait on its pool), so Ctrl-C (`KeyboardInterrupt`) stops a solve at its
/// next progress report instead of at its end. The handler's exception is raised once the work
/// has stopped; its result is then dropped.
pub(crate) fn interruptible<T: Send>(
    py: Python<'_>,
    progress: Option<&PyProgress>,
    work: impl FnOnce(&dyn Observer) -> T + Send,
) -> PyResult<T> {
    let cancel = AtomicBool::new(false);
    let observer = Cancellable {
        inner: match progress {
            Some(p) => p,
            None => &Silent,
        },
        cancel: &cancel,
    };
    let (result, interrupt) = py.detach(|| {
        std::thread::scope(|scope| {
            let waiter = std::thread::current();
            let observer = &observer;
            let worker = std::thread::Builder::new()
                .name("preston-work".into())
                .spawn_scoped(scope, move || {
                    let out = work(observer);
                    waiter.unpark();
                    out
                });
            let worker = match worker {
                Ok(w) => w,
                Err(e) => return (Err(PyErr::from(e)), None),
            };
            let mut interrupt = None;
            while !worker.is_finished() {
                std::thread::park_timeout(std::time::Duration::from_millis(SIGNAL_CHECK_MS));
                if interrupt.is_none() {
                    if let Err(e) = Python::attach(|py| py.check_signals()) {
                        cancel.store(true, Ordering::Relaxed);
                        interrupt = Some(e);
                    }
                }
            }
            match worker.join() {
                Ok(out) => (Ok(out), interrupt),
                Err(panic) => std::panic::resume_unwind(panic),
            }
        })
    });
    match interrupt {
        Some(e) => Err(e),
        None => result,
    }
}
