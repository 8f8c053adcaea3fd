"""Type stubs of the native module ``preston._preston`` (units: mm, nm, s, nm/s, mm/min)."""

from typing import Any, Callable, Optional, Tuple

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

class PrestonError(Exception):
    """Base class of every Preston error; the message is Preston's (file, line, field)."""

class InputError(PrestonError):
    """Bad input: unreadable file, malformed map/TIF/job, invalid option or array."""

class SolverError(PrestonError):
    """The engine failed numerically."""

class NotConvergedError(PrestonError):
    """The solver stopped before converging (only with ``require_converged=True``)."""

class SolveResult:
    """A finished solve (wrapped by :class:`preston.SolveResult`)."""

    @property
    def dwell_s(self) -> F64:
        """Dwell time at each dwell point, s (path order)."""
    @property
    def feed_mm_per_min(self) -> F64:
        """Feed into each dwell point, mm/min."""
    @property
    def ds_mm(self) -> F64:
        """Path length each dwell point stands for, mm."""
    @property
    def dwell_x_mm(self) -> F64: ...
    @property
    def dwell_y_mm(self) -> F64: ...
    @property
    def map_x_mm(self) -> F64: ...
    @property
    def map_y_mm(self) -> F64: ...
    @property
    def z_nm(self) -> F64:
        """Map error, nm."""
    @property
    def removal_nm(self) -> F64:
        """Predicted removal at the map points, nm."""
    @property
    def residual_nm(self) -> F64:
        """``z - removal`` with its mean removed, nm."""
    @property
    def report_json(self) -> str:
        """The content of report.json."""
    @property
    def status(self) -> str: ...
    @property
    def converged(self) -> bool: ...
    def write(self, out_dir: str) -> None:
        """Writes dwell.csv, residual.csv, report.json into ``out_dir`` (each whole or not at all)."""

def load_job(path: str) -> str:
    """A job file (TOML) as JSON text, relative paths resolved against its directory."""

def check_job(job_json: str, base_dir: Optional[str] = None, job_name: str = "<job>") -> str:
    """A job (JSON) checked and normalised, relative paths resolved against ``base_dir``."""

def read_map(source_json: str) -> Tuple[F64, F64, F64, str]:
    """A map read with a ``[map]`` table's options: ``(x_mm, y_mm, z_nm, how_read_json)``."""

def solve(
    job_json: str,
    job_name: str = "<python>",
    map_xyz: Optional[F64] = None,
    tif_xyr: Optional[F64] = None,
    dwell_xy: Optional[F64] = None,
    progress: Optional[Callable[[dict], Any]] = None,
) -> SolveResult:
    """Solves a job (JSON) with optional ``(N, 3)`` map / TIF and ``(N, 2)`` dwell arrays."""

def _raise_numerical() -> None: ...

def simulate(
    map_xy: F64,
    dwell_xy: F64,
    dwell_s: F64,
    tif_json: str = "{}",
    tif_xyr: Optional[F64] = None,
    samples_per_point: Optional[int] = None,
    progress: Optional[Callable[[dict], Any]] = None,
) -> F64:
    """Removal (nm) at ``(N, 2)`` map points of a dwell program (discrete, or continuous with
    ``samples_per_point``)."""

def raster(
    x_min_mm: float, x_max_mm: float, y_min_mm: float, y_max_mm: float, pitch_mm: float, along: str
) -> Tuple[F64, F64]:
    """A serpentine raster over a box, ``(x_mm, y_mm)`` in path order."""

def fit(
    points_xyz: F64,
    order: int = 10,
    norm_radius_mm: Optional[float] = None,
    curvature_per_mm: float = 0.0,
    conic: float = 0.0,
    fit_conic: bool = False,
) -> Tuple[str, str, F64]:
    """XY-polynomial fit of ``(N, 3)`` points (mm): ``(surface_json, summary_json, residual_nm)``."""

def nc(
    dwell_xy: F64,
    dwell_s: F64,
    settings_json: str = "{}",
    surface_file: Optional[str] = None,
    notes: list = ...,
) -> Tuple[str, int]:
    """G-code for a dwell plan: ``(program_text, feed_blocks)``."""
