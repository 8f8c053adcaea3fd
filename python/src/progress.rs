//! The engine's progress reported to a Python callback (`progress=` of `preston.solve`), the
//! interpreter taken only for the call.

use crate::*;

/// Forwards the engine's progress to a Python callable, at most about once per percent of a
/// stage and once per solver iteration. An exception raised by the callable is kept (the first
/// one) and raised when the work returns; later calls are skipped.
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
}
