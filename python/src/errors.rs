//! Preston's errors as Python exceptions: the `PrestonError` hierarchy, input errors that are
//! also the builtin they are (`ValueError`, `OSError`, `FileNotFoundError`), and messages in
//! Python's terms (the keyword, not a JSON position).

use crate::*;

create_exception!(
    preston,
    PrestonError,
    PyException,
    "Base class of every error Preston raises; the message is Preston's (file, line, field)."
);
/// The Python types of the input errors, made at import (they subclass Python's builtins as well
/// as [`PrestonError`], which a `create_exception!` type cannot).
pub(crate) static INPUT_TYPES: PyOnceLock<[Py<PyType>; 3]> = PyOnceLock::new();

/// `InputError(PrestonError, ValueError)`, `InputFileError(InputError, OSError)` and
/// `InputFileNotFoundError(InputFileError, FileNotFoundError)`.
pub(crate) fn make_input_types(py: Python<'_>) -> PyResult<[Py<PyType>; 3]> {
    let builtins = py.import("builtins")?;
    let type_ = builtins.getattr("type")?;
    let make = |name: &str, bases: Bound<'_, PyTuple>, doc: &str| -> PyResult<Py<PyType>> {
        let dict = PyDict::new(py);
        dict.set_item("__module__", "preston")?;
        dict.set_item("__doc__", doc)?;
        Ok(type_
            .call1((name, bases, dict))?
            .cast_into::<PyType>()?
            .unbind())
    };
    let input = make(
        "InputError",
        PyTuple::new(
            py,
            [
                py.get_type::<PrestonError>().into_any(),
                py.get_type::<PyValueError>().into_any(),
            ],
        )?,
        "Bad input: a malformed map/TIF/job, an invalid option, keyword or array. A ValueError.",
    )?;
    let file = make(
        "InputFileError",
        PyTuple::new(
            py,
            [
                input.bind(py).clone().into_any(),
                py.get_type::<PyOSError>().into_any(),
            ],
        )?,
        "A file that cannot be opened, read or written. An InputError and an OSError.",
    )?;
    let missing = make(
        "InputFileNotFoundError",
        PyTuple::new(
            py,
            [
                file.bind(py).clone().into_any(),
                py.get_type::<PyFileNotFoundError>().into_any(),
            ],
        )?,
        "A file that does not exist. An InputFileError and a FileNotFoundError.",
    )?;
    Ok([input, file, missing])
}

/// Raises the input errors ([`make_input_types`]).
pub(crate) struct InputError;

impl InputError {
    /// `InputError(msg)`.
    pub(crate) fn new_err(msg: impl Into<String>) -> PyErr {
        input_err(0, msg.into())
    }
}

/// The input error of kind `k` (0 input, 1 file, 2 missing file) with `msg`.
pub(crate) fn input_err(k: usize, msg: String) -> PyErr {
    Python::attach(
        |py| match INPUT_TYPES.get_or_try_init(py, || make_input_types(py)) {
            Ok(types) => PyErr::from_type(types[k].bind(py).clone(), msg),
            Err(e) => e,
        },
    )
}

create_exception!(
    preston,
    SolverError,
    PrestonError,
    "The engine failed numerically (a factorisation or solver broke down)."
);
create_exception!(
    preston,
    NotConvergedError,
    PrestonError,
    "The solver stopped before converging (raised only with require_converged=True)."
);

/// Preston's I/O error as the matching Python exception.
pub(crate) fn to_py(e: preston_io::Error) -> PyErr {
    let numerical = matches!(
        &e,
        preston_io::Error::Engine {
            source: preston_solver::Error::Numerical { .. },
            ..
        } | preston_io::Error::Solver(preston_solver::Error::Numerical { .. })
    );
    if numerical {
        return SolverError::new_err(e.to_string());
    }
    match &e {
        preston_io::Error::Io { source, .. } => {
            let k = if source.kind() == std::io::ErrorKind::NotFound {
                2
            } else {
                1
            };
            input_err(k, e.to_string())
        }
        _ => InputError::new_err(e.to_string()),
    }
}

/// A job's JSON as Python gave it, the error in Python's terms: the keyword of `solve` (or the
/// job key) at fault and serde's message without its position in the internal JSON.
pub(crate) fn json_error_in_python_terms(json: &str, e: &serde_json::Error) -> String {
    let (msg, path) = message_and_key_path(json, e);
    let dotted = path.join(".");
    match python_keyword(&dotted) {
        Some(kw) => format!("{kw}: {msg} (job key {dotted})"),
        None if dotted.is_empty() => msg,
        None => format!("key {dotted}: {msg}"),
    }
}

/// serde's message without its position in the JSON, and the keys leading to the value at fault
/// (an unknown field's path is its object's plus the field).
pub(crate) fn message_and_key_path(json: &str, e: &serde_json::Error) -> (String, Vec<String>) {
    let mut msg = e.to_string();
    if let Some(k) = msg.rfind(" at line ") {
        msg.truncate(k);
    }
    let offset = json
        .split_inclusive('\n')
        .take(e.line().saturating_sub(1))
        .map(str::len)
        .sum::<usize>()
        + e.column().saturating_sub(1);
    let mut path = key_path_at(json, offset);
    if let Some(field) = msg
        .strip_prefix("unknown field `")
        .and_then(|r| r.split('`').next())
    {
        if path.last().map(String::as_str) != Some(field) {
            path.push(field.to_string());
        }
    }
    (msg, path)
}

/// The keyword of `preston.solve` a job key comes from, where there is one.
pub(crate) fn python_keyword(dotted: &str) -> Option<String> {
    const KEYS: [(&str, &str); 16] = [
        ("machine.v_max_mm_per_min", "v_max"),
        ("machine.v_min_mm_per_min", "v_min"),
        ("machine.a_max_mm_per_s2", "a_max"),
        ("machine.accel_method", "accel_method"),
        ("machine.corner_angle_deg", "corner_angle_deg"),
        ("objective.rho", "rho"),
        ("objective.lambda", "lambda_"),
        ("dwell.raster_pitch_mm", "raster_pitch_mm"),
        ("dwell.raster_along", "raster_along"),
        ("edge.method", "edge"),
        ("edge.width_mm", "edge_width_mm"),
        ("surface.tif_frame", "tif_frame"),
        ("solver.first_order_tolerance", "tolerance"),
        ("solver.first_order_max_iterations", "max_iterations"),
        ("solver.min_time", "min_time"),
        ("tif.file", "tif"),
    ];
    if let Some((_, kw)) = KEYS.iter().find(|(k, _)| *k == dotted) {
        return Some(format!("{kw}="));
    }
    if let Some(rest) = dotted.strip_prefix("tif.gaussian.") {
        return Some(format!("gaussian['{rest}']"));
    }
    if dotted == "tif.gaussian" {
        return Some("gaussian=".into());
    }
    if let Some(rest) = dotted.strip_prefix("map.") {
        return Some(format!("map_options['{rest}']"));
    }
    if let Some(rest) = dotted.strip_prefix("solver.") {
        return Some(format!("{rest}="));
    }
    None
}

/// The keys leading to byte `offset` of a JSON text (`["tif", "gaussian", "peak"]`); array
/// elements appear as their index.
pub(crate) fn key_path_at(json: &str, offset: usize) -> Vec<String> {
    enum Frame {
        Object(Option<String>),
        Array(usize),
    }
    let bytes = json.as_bytes();
    let mut stack: Vec<Frame> = Vec::new();
    let mut i = 0;
    let mut last_string: Option<String> = None;
    while i < bytes.len() && i < offset {
        match bytes[i] {
            b'"' => {
                let start = i + 1;
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' {
                    if bytes[i] == b'\\' {
                        i += 1;
                    }
                    i += 1;
                }
                last_string = json.get(start..i.min(json.len())).map(str::to_string);
            }
            b':' => {
                if let Some(Frame::Object(key)) = stack.last_mut() {
                    *key = last_string.take();
                }
            }
            b'{' => stack.push(Frame::Object(None)),
            b'[' => stack.push(Frame::Array(0)),
            b'}' | b']' => {
                stack.pop();
            }
            b',' => match stack.last_mut() {
                Some(Frame::Array(k)) => *k += 1,
                Some(Frame::Object(key)) => *key = None,
                None => {}
            },
            _ => {}
        }
        i += 1;
    }
    stack
        .into_iter()
        .filter_map(|f| match f {
            Frame::Object(k) => k,
            Frame::Array(k) => Some(k.to_string()),
        })
        .collect()
}

/// An engine error on data named `what` (an array argument) as a Python exception.
pub(crate) fn engine_to_py(what: &str, e: preston_solver::Error) -> PyErr {
    to_py(preston_io::Error::engine(what, e))
}
