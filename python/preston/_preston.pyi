"""Type stubs of the native module ``preston._preston`` (units: mm, nm, s, nm/s, mm/min)."""

from typing import Any, Callable, List, Optional, Tuple

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

__version__: str

class PrestonError(Exception):
    """Base class of every Preston error; the message is Preston's (file, line, field)."""

class InputError(PrestonError, ValueError):
    """Bad input: malformed map/TIF/job, invalid keyword, option or array."""

class InputFileError(InputError, OSError):
    """A file that cannot be opened, read or written."""

class InputFileNotFoundError(InputFileError, FileNotFoundError):
    """A file that does not exist."""

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
        """Predicted removal at the map points as the report states it (the program as executed
        where the solve executes it), nm."""
    @property
    def residual_nm(self) -> F64:
        """``z - removal`` with its mean removed (its RMS is ``rms_after_nm``), nm."""
    @property
    def model_removal_nm(self) -> F64:
        """The model's removal at the programmed feeds, nm."""
    @property
    def model_residual_nm(self) -> F64:
        """The model's residual at the programmed feeds with its mean removed, nm."""
    @property
    def report_json(self) -> str:
        """The content of report.json."""
    @property
    def status(self) -> str: ...
    @property
    def converged(self) -> bool: ...
    @property
    def program_check_json(self) -> Optional[str]:
        """What the program of the job's machine does with the plan (JSON), or None."""
    def write(self, out_dir: str, plots: bool = False) -> List[str]:
        """Writes dwell.csv, residual.csv, report.json (and with ``plots`` the figures and psd.csv)
        into ``out_dir``, all committed together; returns the notes on figures left out."""
    def write_plots(self, out_dir: str, along: Optional[str] = None) -> Tuple[List[str], List[str]]:
        """Writes the figures of ``preston solve --plots`` (PNG) and psd.csv into ``out_dir``:
        ``(files, notes)``."""
    def psd(self, along: Optional[str] = None) -> Tuple[F64, F64, F64, str]:
        """1-D PSDs along ``along`` (``"x"``/``"y"``; default the job's raster direction):
        ``(frequency_per_mm, error_psd_nm2_mm, residual_psd_nm2_mm, info_json)``."""

def load_job(path: str) -> str:
    """A job file (TOML) as JSON text, relative paths resolved against its directory."""

def check_job(job_json: str, base_dir: Optional[str] = None, job_name: str = "<job>") -> str:
    """A job (JSON) checked and normalised, relative paths resolved against ``base_dir``."""

def apply_overrides(
    job_json: str, overrides_json: str, base_dir: str, job_name: str = "<python>"
) -> str:
    """The job (JSON) with the keywords of ``solve`` applied by the engine's override layer."""

def read_map(source_json: str) -> Tuple[F64, F64, F64, str]:
    """A map read with a ``[map]`` table's options: ``(x_mm, y_mm, z_nm, how_read_json)``."""

def influence_matrix(
    job_json: str,
    job_name: str = "<python>",
    map_xyz: Optional[np.ndarray] = None,
    tif_xyr: Optional[np.ndarray] = None,
    dwell_xy: Optional[np.ndarray] = None,
) -> Tuple[int, int, int, List[int], List[int], np.ndarray, List[np.ndarray]]: ...
def solve(
    job_json: str,
    job_name: str = "<python>",
    map_xyz: Optional[F64] = None,
    tif_xyr: Optional[F64] = None,
    dwell_xy: Optional[F64] = None,
    progress: Optional[Callable[[dict], Any]] = None,
    threads: Optional[int] = None,
) -> SolveResult:
    """Solves a job (JSON) with optional ``(N, 3)`` map / TIF and ``(N, 2)`` dwell arrays, on
    ``threads`` engine threads (None: the global pool)."""

def _raise_numerical() -> None: ...
def run_cli(argv: List[str]) -> int:
    """The `preston` command line on argv (program name first); its exit code."""
def sample_job(dir: str, overwrite: bool = False) -> Any:
    """Writes the sample job into dir; its job file."""

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

def tif_model(
    model: str,
    params_json: str,
    pitch_mm: float,
    part_radius_mm: Optional[float] = None,
    surface_json: Optional[str] = None,
    at_mm: Optional[Tuple[float, float]] = None,
) -> Tuple[F64, F64, F64, str]:
    """A ``"hertz"``, ``"bonnet"`` or ``"gaussian"`` TIF sampled at ``pitch_mm`` (mm):
    ``(x_mm, y_mm, rate_nm_per_s, summary_json)``."""

def tif_grid(
    tif_xyr: F64,
    pitch_mm: Optional[float] = None,
    recentre: bool = False,
    peak_nm_per_s: Optional[float] = None,
    volume_mm3_per_min: Optional[float] = None,
) -> Tuple[F64, F64, F64, str]:
    """A measured TIF grid resampled, recentred and scaled: ``(x_mm, y_mm, rate_nm_per_s, summary_json)``."""

def tif_spot(
    before_xyz: F64,
    after_xyz: F64,
    dwell_s: float,
    crop_radius_mm: Optional[float] = None,
    remove_tilt: bool = False,
    recentre: bool = False,
    fit_gaussian_model: bool = False,
) -> Tuple[F64, F64, F64, str]:
    """The TIF of a removal spot (maps in nm, dwell in s): ``(x_mm, y_mm, rate_nm_per_s, summary_json)``."""

def path_spiral(
    centre_mm: Tuple[float, float], radius_mm: float, pitch_mm: float, step_mm: float
) -> Tuple[F64, F64]:
    """An Archimedes spiral, ``(x_mm, y_mm)`` in path order."""

def path_random(
    x_range_mm: Tuple[float, float], y_range_mm: Tuple[float, float], settings_json: str
) -> Tuple[F64, F64, str]:
    """A pseudo-random unicursal path: ``(x_mm, y_mm, summary_json)``."""

def path_edge_offset(edge_xy: F64, settings_json: str) -> Tuple[F64, F64, str]:
    """The edge-offset trajectory inside a closed edge (mm): ``(x_mm, y_mm, summary_json)``."""

#: The seven columns of ``preston path``'s CSV: x_mm, y_mm, z_mm, tx, ty, tz, ds_mm.
PathColumns = Tuple[F64, F64, F64, F64, F64, F64, F64]

def path_lines(
    x_range_mm: Tuple[float, float],
    y_range_mm: Tuple[float, float],
    pitch_mm: float,
    along: str = "x",
    iteration: Optional[int] = None,
    step_mm: Optional[float] = None,
    margin_mm: float = 0.0,
    arc_radius_mm: Optional[float] = None,
    arc_tolerance_um: float = 1.0,
    aperture_xy: Optional[F64] = None,
    surface_json: Optional[str] = None,
) -> Tuple[PathColumns, str]:
    """A raster (``iteration`` None) or intersection raster (mm; arc tolerance um), clipped to an
    ``(N, 2)`` aperture and projected onto a surface: ``(columns, summary_json)``."""

def path_chord_height(
    surface_json: str,
    line_x_mm: float,
    y_range_mm: Tuple[float, float],
    tool_radius_mm: float,
    eps_um: Tuple[float, float],
    grow_mm: float = 0.10,
    shrink_mm: float = 0.02,
) -> Tuple[PathColumns, str, F64, F64]:
    """Equal chord-height points along x = line_x_mm on a surface: ``(columns, summary_json,
    steps_mm, chord_heights_mm)``."""

def path_project(points_xy: F64, surface_json: Optional[str] = None) -> PathColumns:
    """``(N, 2)`` path points (mm) projected onto a surface (flat without one)."""

def register(
    surface_json: str, points_xyz: F64, settings_json: str
) -> Tuple[str, F64, F64, F64, F64, F64]:
    """ICP registration: ``(transform_json, design_x_mm, design_y_mm, form_error_nm,
    points_xyz_mm (flat), weights)``."""

def simulate_program(
    map_json: str,
    program: str,
    tif_json: str = "{}",
    tif_xyr: Optional[F64] = None,
    a_max_mm_per_s2: Optional[float] = None,
    corner_angle_deg: float = 60.0,
    dialect: Optional[str] = None,
    sample_step_mm: Optional[float] = None,
    surface_json: Optional[str] = None,
    tool_radius_mm: float = 0.0,
    progress: Optional[Callable[[dict], Any]] = None,
) -> Tuple[F64, F64, F64, F64, F64, str, str]:
    """A G-code program run on the machine: ``(map_x_mm, map_y_mm, z_nm, removal_nm, residual_nm,
    report_json, check_json)``."""

def iterate(
    settings_json: str,
    surface_json: Optional[str] = None,
    tif_json: str = "{}",
    tif_xyr: Optional[F64] = None,
    part_json: str = "{}",
    map_xyz: Optional[F64] = None,
    iteration: int = 0,
    progress: Optional[Callable[[dict], Any]] = None,
    threads: Optional[int] = None,
) -> Tuple[str, F64, F64, F64, Optional[Tuple[F64, F64, F64, F64, F64, F64]]]:
    """The polishing loop: ``(outcome_json, final_x_mm, final_y_mm, final_z_nm, last_run)``."""

def calibrate(
    before_json: str,
    after_json: str,
    program: str,
    tif_json: str = "{}",
    tif_xyr: Optional[F64] = None,
    tif_file: Optional[str] = None,
    a_max_mm_per_s2: Optional[float] = None,
    corner_angle_deg: float = 60.0,
    dialect: Optional[str] = None,
    settings_json: str = "{}",
    out: Optional[str] = None,
    plot_format: Optional[str] = None,
) -> Tuple[str, Tuple[F64, F64, F64], bool]:
    """The tool that ran, from the maps before and after a run and its program: ``(record_json,
    (tif_x_mm, tif_y_mm, tif_rate_nm_per_s), converged)``, the record as ``calibration.json``."""

def shop(
    surface_json: str,
    program: Optional[str] = None,
    tif_json: str = "{}",
    tif_xyr: Optional[F64] = None,
    a_max_mm_per_s2: Optional[float] = None,
    corner_angle_deg: float = 60.0,
    dialect: Optional[str] = None,
    tool_json: str = "{}",
    noise_rms_nm: float = 0.3,
    seed: int = 1,
    out: Optional[str] = None,
) -> Tuple[str, Tuple[F64, F64, F64, F64]]:
    """A visit to the virtual shop: ``(record_json, (x_mm, y_mm, surface_after_nm,
    measured_nm))``, the record as ``shop.json``."""
