"""Preston: dwell times for deterministic sub-aperture polishing, from Python.

The same engine as the ``preston`` command line, with numpy arrays in and out and no files in
between. Units everywhere: lengths mm, heights and removal nm, times s, removal rates nm/s, feeds
mm/min.

* :func:`solve` -- dwell times and feeds for an error map, a tool influence function (TIF) and a
  dwell path (given points or a generated raster), with every solver, operator and limit option
  of ``preston solve``.
* :func:`read_map` -- any map format the CLI reads (CSV, XYZ text, NumPy ``.npy``, Zygo ``.dat``
  / ``.datx``, 4D ``.h5``) with its options (units, columns, pitch, aperture, form removal).
* :func:`tif_gaussian`, :func:`tif_hertz`, :func:`tif_bonnet`, :func:`tif_grid`,
  :func:`tif_spot` -- TIFs from process models, measured grids and removal spots.
* :func:`raster`, :func:`path_spiral`, :func:`path_random`, :func:`path_edge_offset` -- paths
  (x_mm, y_mm); :func:`path_raster`, :func:`path_intersection` (crossed rasters, arc turns,
  clear-aperture clipping), :func:`path_chord_height` and :func:`path_project` -- paths with
  every option of ``preston path``, projected onto a design surface (:class:`ToolPath`).
* :meth:`SolveResult.write_plots` / :meth:`SolveResult.psd` -- the figures of
  ``preston solve --plots`` and the PSDs of ``psd.csv``.
* :func:`register` -- installation and form error of measured points (ICP);
  :func:`simulate_program` -- the removal a G-code program produces on the machine;
  :func:`iterate` -- the measure-register-solve-polish loop.
* :func:`calibrate` -- the tool that ran, learned from a run's measured change (``solve(...,
  calibration=)`` plans the next run with it); :func:`shop` -- a virtual shop to rehearse the
  loop.
* :func:`batch` / :func:`grid` -- many solves (job dicts, job files, a parameter grid over one
  job) on a ``dask.distributed`` cluster, outputs written atomically per job.

Errors are raised as :class:`PrestonError` subclasses carrying Preston's message (the keyword,
file, line or field at fault): :class:`InputError` (bad input; also a ``ValueError``),
:class:`InputFileError` (a file that cannot be read or written; also an ``OSError``, and
:class:`InputFileNotFoundError` a ``FileNotFoundError``), :class:`SolverError` (numerical
failure), :class:`NotConvergedError` (only when ``require_converged=True``).

A worked example from a measured map to the program, the plots and the report:
``docs/tutorial.py``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Callable, List, Mapping, NamedTuple, Optional, Sequence, Tuple, Union

import numpy as np

from . import _preston
from ._preston import (
    InputError,
    InputFileError,
    InputFileNotFoundError,
    NotConvergedError,
    PrestonError,
    SolverError,
)
from ._preston import __version__  # the same as `preston --version`

__all__ = [
    "__version__",
    "solve",
    "read_map",
    "load_job",
    "batch",
    "grid",
    "simulate",
    "raster",
    "fit",
    "nc",
    "tif_gaussian",
    "tif_hertz",
    "tif_bonnet",
    "tif_grid",
    "tif_spot",
    "path_spiral",
    "path_random",
    "path_edge_offset",
    "path_raster",
    "path_intersection",
    "path_chord_height",
    "path_project",
    "ToolPath",
    "register",
    "simulate_program",
    "iterate",
    "calibrate",
    "shop",
    "SolveResult",
    "PrestonError",
    "InputError",
    "InputFileError",
    "InputFileNotFoundError",
    "SolverError",
    "influence_matrix",
    "sample_job",
    "Grid",
    "NotConvergedError",
]

PathLike = Union[str, "os.PathLike[str]"]
ArrayLike = Any

#: The options of a job's ``[map]`` table that :func:`read_map` and ``map_options`` accept.
MAP_OPTIONS = ("format", "columns", "units", "pitch_mm", "aperture", "remove")


class Grid(NamedTuple):
    """Values of a map on its lattice: ``values[j, i]`` at ``(x_mm[i], y_mm[j])``, NaN where the
    lattice has no point (outside the aperture or dropped)."""

    x_mm: np.ndarray
    y_mm: np.ndarray
    values: np.ndarray


def _grid(x: np.ndarray, y: np.ndarray, v: np.ndarray, name: str) -> Grid:
    """``v`` at the points ``(x, y)`` on their lattice (the smallest step between distinct
    coordinates, within 1e-6 of it)."""
    x, y, v = (np.asarray(a, dtype=np.float64) for a in (x, y, v))
    if x.size < 2:
        raise InputError(f"{name}: fewer than two points, no lattice")

    def axis(c: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        u = np.unique(c)
        if u.size == 1:
            return u, np.zeros(c.size, dtype=np.int64)
        step = np.min(np.diff(u))
        k = np.rint((c - u[0]) / step)
        if np.max(np.abs((c - u[0]) / step - k)) > 1e-6 or k.max() + 1 > 16 * c.size:
            raise InputError(f"{name}: the points are not on a lattice")
        n = int(k.max()) + 1
        return u[0] + step * np.arange(n), k.astype(np.int64)

    xs, ix = axis(x)
    ys, iy = axis(y)
    g = np.full((ys.size, xs.size), np.nan)
    g[iy, ix] = v
    return Grid(xs, ys, g)


class SolveResult:
    """The outcome of :func:`solve`.

    Attributes (numpy ``float64`` arrays unless stated):

    * ``dwell_s`` -- dwell time at each dwell point, s, in path order.
    * ``feed_mm_per_min`` -- feed into each dwell point, mm/min (``60 ds_mm / dwell_s``).
    * ``ds_mm`` -- path length each dwell point stands for, mm.
    * ``dwell_x_mm``, ``dwell_y_mm`` -- the dwell points, mm.
    * ``map_x_mm``, ``map_y_mm``, ``z_nm`` -- the map points kept, mm, and their error, nm.
    * ``removal_nm`` -- predicted removal at each map point as the report states it: the
      program as the controller runs it where the solve executes it (an acceleration limit),
      else the model's at the programmed feeds, nm.
    * ``residual_nm`` -- ``z_nm - removal_nm`` with its mean removed (as in residual.csv; its
      RMS is ``report["rms_after_nm"]``), nm.
    * ``model_removal_nm``, ``model_residual_nm`` -- the model's removal and residual at the
      programmed feeds (as in residual_model.csv where a program is executed; otherwise equal
      to ``removal_nm`` and ``residual_nm``), nm.
    * ``report`` -- dict with the keys of ``report.json`` (RMS/PV before and after in nm, total
      dwell s, machining time s, solver, status, iterations, warnings, ...).
    * ``status`` (str), ``converged`` (bool) -- the solver's status.
    * ``program_check`` -- dict: what the program of the job's machine (its ``[nc]`` profile and
      limits) does with the plan, as ``preston solve --json`` prints it (machining time s, feed
      blocks, the programmed and accelerated stretch times against the plan); ``None`` when no
      program can deliver the plan.

    Where the map is on a lattice, :meth:`grid` gives any map quantity as a 2-D array with its x
    and y axes (``error_grid``, ``removal_grid`` and ``residual_grid`` for the usual three).
    """

    __slots__ = (
        "_native",
        "dwell_s",
        "feed_mm_per_min",
        "ds_mm",
        "dwell_x_mm",
        "dwell_y_mm",
        "map_x_mm",
        "map_y_mm",
        "z_nm",
        "removal_nm",
        "residual_nm",
        "model_removal_nm",
        "model_residual_nm",
        "report",
        "status",
        "converged",
        "program_check",
    )

    def __init__(self, native: "_preston.SolveResult") -> None:
        self._native = native
        self.dwell_s = native.dwell_s
        self.feed_mm_per_min = native.feed_mm_per_min
        self.ds_mm = native.ds_mm
        self.dwell_x_mm = native.dwell_x_mm
        self.dwell_y_mm = native.dwell_y_mm
        self.map_x_mm = native.map_x_mm
        self.map_y_mm = native.map_y_mm
        self.z_nm = native.z_nm
        self.removal_nm = native.removal_nm
        self.residual_nm = native.residual_nm
        self.model_removal_nm = native.model_removal_nm
        self.model_residual_nm = native.model_residual_nm
        self.report = json.loads(native.report_json)
        self.status = native.status
        self.converged = native.converged
        check = native.program_check_json
        self.program_check = None if check is None else json.loads(check)

    def grid(self, values: str = "residual_nm") -> Grid:
        """The map quantity ``values`` (``"z_nm"``, ``"removal_nm"``, ``"residual_nm"``,
        ``"model_removal_nm"`` or ``"model_residual_nm"``) on the map's lattice: a :class:`Grid`
        ``(x_mm, y_mm, values)`` with ``values[j, i]`` at ``(x_mm[i], y_mm[j])``, NaN where the
        lattice has no point. A map off a lattice raises :class:`InputError`."""
        allowed = ("z_nm", "removal_nm", "residual_nm", "model_removal_nm", "model_residual_nm")
        if values not in allowed:
            raise InputError(f"values={values!r}: one of {', '.join(map(repr, allowed))}")
        return _grid(self.map_x_mm, self.map_y_mm, getattr(self, values), "map")

    @property
    def error_grid(self) -> Grid:
        """The error map on its lattice (:meth:`grid` of ``z_nm``)."""
        return self.grid("z_nm")

    @property
    def removal_grid(self) -> Grid:
        """The predicted removal on the map's lattice."""
        return self.grid("removal_nm")

    @property
    def residual_grid(self) -> Grid:
        """The residual (mean removed) on the map's lattice, as the report states it (the
        program as executed where the solve executes it)."""
        return self.grid("residual_nm")

    @property
    def model_residual_grid(self) -> Grid:
        """The model's residual at the programmed feeds (mean removed) on the map's lattice."""
        return self.grid("model_residual_nm")

    def write(
        self,
        out_dir: PathLike,
        *,
        plots: bool = False,
        report: bool = False,
        color_limits: Optional[Union[str, Tuple[float, float]]] = None,
        plot_format: str = "png",
    ) -> List[str]:
        """Writes ``dwell.csv``, ``residual.csv`` and ``report.json`` (the CLI's files) into
        ``out_dir``, created if needed; with ``plots=True`` the figures and PSD tables of
        ``preston solve --plots`` (see :meth:`write_plots`); with ``report=True``
        ``report.html`` (``preston solve --report``: one self-contained page with the inputs,
        result, machine summary, warnings and figures). ``color_limits``: ``"robust"`` (the
        default), ``"full"`` or ``(lo, hi)`` in nm for the error and residual maps, as
        ``--color-limits``; ``plot_format``: ``"png"`` or ``"svg"``, as ``--plot-format``.
        Everything is staged first and committed together: all the files
        appear, whole, or none. Returns the notes on figures left out (a PSD needs the map on a
        lattice)."""
        if color_limits is not None and not isinstance(color_limits, str):
            try:
                lo, hi = color_limits
                color_limits = f"{float(lo)},{float(hi)}"
            except (TypeError, ValueError):
                raise InputError(
                    f"color_limits={color_limits!r}: 'robust', 'full' or (lo, hi) in nm"
                ) from None
        return list(
            self._native.write(os.fspath(out_dir), plots, report, color_limits, plot_format)
        )

    def write_plots(
        self, out_dir: PathLike, *, along: Optional[str] = None, plot_format: str = "png"
    ) -> Tuple[List[Path], List[str]]:
        """Writes the figures of ``preston solve --plots`` into ``out_dir`` (created if needed),
        committed together: ``error_before.png``, ``removal.png``, ``residual.png`` (nm),
        ``dwell.png`` (s), ``feed.png`` (mm/min) and ``path.png`` at equal mm per pixel (1000 px
        wide), ``tif.png`` (nm/s), and ``psd.png`` (900 x 700 px) with ``psd.csv``: the 1-D PSDs
        of error and residual along ``along`` (``"x"``/``"y"``; default: the job's raster
        direction), the raster pitch marked where it lies on the frequency axis (else named in
        the legend), and the 2-D and azimuthal PSDs with their CSVs.
        ``plot_format="svg"`` writes the figures as SVG (``--plot-format svg``).

        Returns ``(files, notes)``: the paths written and why a figure was left out (no PSD for a
        map off a lattice)."""
        files, notes = self._native.write_plots(os.fspath(out_dir), along, plot_format)
        return [Path(f) for f in files], list(notes)

    def psd(self, along: Optional[str] = None) -> dict:
        """The 1-D power spectral densities behind ``psd.png`` / ``psd.csv``: Welch averages of
        the one-sided PSD along the lattice lines of the map in ``along`` (``"x"``/``"y"``;
        default: the job's raster direction), of the error and of the residual.

        Returns a dict: ``frequency_per_mm`` (1/mm), ``error_psd_nm2_mm`` and
        ``residual_psd_nm2_mm`` (nm^2 mm), float64 arrays (the columns of ``psd.csv``), and
        ``along``, ``segments`` (segments averaged), ``segment_points`` (points per segment) and
        ``pitch_mm`` (the map's lattice pitch). A map off a lattice raises :class:`InputError`."""
        f, before, after, info = self._native.psd(along)
        out = {"frequency_per_mm": f, "error_psd_nm2_mm": before, "residual_psd_nm2_mm": after}
        out.update(json.loads(info))
        return out

    def __repr__(self) -> str:
        r = self.report
        return (
            f"<preston.SolveResult {len(self.dwell_s)} dwell points, status {self.status}, "
            f"RMS {r.get('rms_before_nm', float('nan')):.3f} -> "
            f"{r.get('rms_after_nm', float('nan')):.3f} nm, "
            f"total dwell {r.get('total_dwell_s', float('nan')):.2f} s>"
        )


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, os.PathLike):
        return os.fspath(o)
    raise TypeError(f"{type(o).__name__} is not a job value")


def _dumps(job: Mapping[str, Any]) -> str:
    try:
        return json.dumps(job, default=_json_default, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise InputError(f"job: {e}") from None


def load_job(job: Union[PathLike, Mapping[str, Any]]) -> dict:
    """A job as a dict with the structure of a job file (``[map]``, ``[tif]``, ``[dwell]``,
    ``[machine]``, ``[objective]``, ``[solver]``, ...), every default filled in and every relative
    path made absolute: a TOML file's paths against its directory, a dict's against the current
    directory. Unknown keys raise :class:`InputError` naming them."""
    if isinstance(job, (str, os.PathLike)):
        return json.loads(_preston.load_job(os.fspath(job)))
    if isinstance(job, Mapping):
        text = _preston.check_job(_dumps(job), os.getcwd(), "<job dict>")
        return json.loads(text)
    raise InputError(f"job: expected a path to a job file or a dict, got {type(job).__name__}")


def _columns(a: ArrayLike, k: int, name: str) -> np.ndarray:
    """An ``(N, k)`` float64 array from an array or a sequence of ``k`` 1-D columns."""
    if isinstance(a, (tuple, list)) and len(a) == k and all(np.ndim(c) == 1 for c in a):
        a = np.column_stack([np.asarray(c, dtype=np.float64) for c in a])
    try:
        arr = np.ascontiguousarray(a, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: not a float array ({e})") from None
    if arr.ndim != 2 or arr.shape[1] != k:
        raise InputError(f"{name}: expected an array of shape (N, {k}), got {arr.shape}")
    return arr


def _abs(p: PathLike) -> str:
    return os.path.abspath(os.fspath(p))


_PATH_KEYWORDS = ("map", "tif", "dwell", "warm_start", "surface", "calibration")


def _job_of(
    job: Optional[Union[PathLike, Mapping[str, Any]]],
    *,
    map_xyz: Optional[ArrayLike] = None,
    map_options: Optional[Mapping[str, Any]] = None,
    tif_xyr: Optional[ArrayLike] = None,
    dwell_xy: Optional[ArrayLike] = None,
    **overrides: Any,
) -> Tuple[dict, str, dict]:
    """The job of :func:`solve`'s arguments: the job dict, its name and the arrays. The keywords
    in ``overrides`` go through the engine's override layer (the one the CLI's flags go
    through); the arrays and ``map_options`` are this package's own."""
    j = load_job(job) if job is not None else load_job({})
    name = os.fspath(job) if isinstance(job, (str, os.PathLike)) else "<python>"
    given = {k: v for k, v in overrides.items() if v is not None}
    for k in _PATH_KEYWORDS:
        if k in given:
            given[k] = os.fspath(given[k])
    if "gaussian" in given:
        given["gaussian"] = _gaussian(given["gaussian"])
    if "map" in given and map_xyz is not None:
        raise InputError("give map= (a file) or map_xyz= (an array), not both")
    if tif_xyr is not None and ("tif" in given or "gaussian" in given):
        raise InputError("give one of tif=, tif_xyr=, gaussian=")
    if dwell_xy is not None and "dwell" in given:
        raise InputError("give dwell= (a file) or dwell_xy= (an array), not both")
    if dwell_xy is not None:
        # The array takes the dwell file's place in the engine's rule "a file or a raster".
        given["dwell"] = "dwell_xy"
    if given:
        j = json.loads(_preston.apply_overrides(_dumps(j), _dumps(given), os.getcwd(), name))

    m = j.get("map") or {}
    if map_options:
        unknown = sorted(set(map_options) - set(MAP_OPTIONS))
        if unknown:
            raise InputError(f"map_options: unknown {unknown} (known: {', '.join(MAP_OPTIONS)})")
        m.update(_map_options(map_options))
    arrays: dict = {}
    if map_xyz is not None:
        if m.get("aperture") or m.get("remove"):
            raise InputError(
                "map_xyz: aperture and remove apply to a map file; read it with "
                "preston.read_map(path, aperture=..., remove=...) and pass the result"
            )
        m["file"] = None
        arrays["map_xyz"] = _columns(map_xyz, 3, "map_xyz")
    j["map"] = m
    if tif_xyr is not None:
        # The grid replaces the TIF's source; what the job knows of the tool stays with it.
        known = ("calibration", "rate_sigma", "width_sigma", "offset_sigma_mm")
        t = j.get("tif") or {}
        j["tif"] = {"file": None, "gaussian": None, **{k: t[k] for k in known if t.get(k) is not None}}
        arrays["tif_xyr"] = _columns(tif_xyr, 3, "tif_xyr")
    if dwell_xy is not None:
        d = j.get("dwell") or {}
        d["file"], d["raster_pitch_mm"] = None, None
        j["dwell"] = d
        arrays["dwell_xy"] = _columns(dwell_xy, 2, "dwell_xy")
    return j, name, arrays


def _gaussian(g: Mapping[str, Any]) -> dict:
    """A Gaussian TIF dict with the CLI's default truncation (3 sigma) filled in."""
    try:
        out = dict(g)
    except (TypeError, ValueError):
        raise InputError(
            f"gaussian={g!r}: a dict of sigma_mm, peak_rate_nm_per_s "
            "(and optionally truncation_radius_mm)"
        ) from None
    if out.get("truncation_radius_mm") is None and isinstance(out.get("sigma_mm"), (int, float)):
        out["truncation_radius_mm"] = 3.0 * float(out["sigma_mm"])
    return out


def influence_matrix(
    job: Optional[Union[PathLike, Mapping[str, Any]]] = None, **kwargs: Any
) -> "scipy.sparse.csc_matrix":  # noqa: F821
    """The influence matrix ``R`` (nm/s per dwell point) of the problem :func:`solve` would
    build from the same arguments (``job`` and the keywords of :func:`solve` for the map, TIF,
    dwell points and edge), as a ``scipy.sparse.csc_matrix`` of shape ``(m, n)``: row ``i`` is
    map point ``i`` (``result.map_x_mm[i]``), column ``j`` dwell point ``j`` in path order, so the
    predicted removal of dwell times ``t`` (s) is ``R @ t`` (nm). Rows of an edge extension
    (``edge=``) come after the ``m`` map rows and are left out. For your own optimiser: minimise
    ``|R t - z - c|`` over ``t >= 0`` and the piston ``c``.

    The matrix is always assembled (whatever ``operator=`` says); needs scipy."""
    try:
        import scipy.sparse as sp
    except ImportError as e:  # pragma: no cover - scipy is a test requirement
        raise ImportError(
            "preston.influence_matrix needs scipy, an optional dependency of preston-dwell: "
            "pip install 'preston-dwell[scipy]' (or pip install scipy)"
        ) from e
    j, name, arrays = _job_of(job, **kwargs)
    m, rows, cols, indptr, indices, data, _points = _preston.influence_matrix(
        _dumps(j), name, **arrays
    )
    r = sp.csc_matrix(
        (np.asarray(data), np.asarray(indices, dtype=np.int64), np.asarray(indptr, dtype=np.int64)),
        shape=(rows, cols),
    )
    return r[:m, :] if rows > m else r


def solve(
    job: Optional[Union[PathLike, Mapping[str, Any]]] = None,
    *,
    map_xyz: Optional[ArrayLike] = None,
    map_options: Optional[Mapping[str, Any]] = None,
    tif_xyr: Optional[ArrayLike] = None,
    dwell_xy: Optional[ArrayLike] = None,
    progress: Optional[Callable[[dict], Any]] = None,
    require_converged: bool = False,
    threads: Optional[int] = None,
    **overrides: Any,
) -> SolveResult:
    """Dwell times and feeds: the engine of ``preston solve``, arrays in and out.

    ``job`` is a job file (TOML) or a dict of the same structure. The other keywords override it
    through the engine's override layer, the one the CLI's flags go through (``Overrides`` in
    ``preston-io``): each flag of ``preston solve`` that changes the job is a keyword of the same
    name with ``_`` for ``-`` (``--raster-pitch-mm``: ``raster_pitch_mm``; the feeds and
    acceleration also as ``v_max``, ``v_min``, ``a_max``, and ``--lambda`` as ``lambda_``), and an
    unknown keyword raises :class:`InputError` naming the known ones. ``None`` leaves the job's
    key as it is. The arrays and ``map_options`` are this package's own:

    * map: ``map`` (a file, any format of :func:`read_map`, read with ``map_options``) or
      ``map_xyz`` (an ``(N, 3)`` array of x_mm, y_mm, z_nm, or a tuple ``(x_mm, y_mm, z_nm)`` such
      as :func:`read_map` returns).
    * TIF: ``tif`` (CSV ``x_mm,y_mm,rate_nm_per_s``), ``tif_xyr`` (``(N, 3)`` array x_mm, y_mm,
      rate_nm_per_s on a regular grid) or ``gaussian`` (``dict(sigma_mm=, peak_rate_nm_per_s=,
      truncation_radius_mm=)``).
    * dwell points: ``dwell`` (CSV ``x_mm,y_mm`` in path order), ``dwell_xy`` (``(N, 2)`` array,
      mm) or ``raster_pitch_mm`` (a serpentine raster at this pitch, mm, over the map extended by
      the TIF radius; lines along ``raster_along`` = ``"x"`` or ``"y"``).
    * limits: ``v_max`` / ``v_min`` (feed, mm/min; ``v_max`` required), ``a_max`` (acceleration
      along a line, mm/s^2), ``accel_method`` (``"correction-passes"``, the default: the plan
      re-solved against the program executed at the limit, the best part as made;
      ``"squared-speed"``, ``"scp-qp"`` or ``"squared-speed-then-scp-qp"``: the limit in the
      plan's own feeds; as ``--accel-method``), ``corner_angle_deg`` (turns splitting lines,
      degrees).
    * objective: ``rho`` (weight of total dwell, nm^2/s), ``lambda_`` (weight of dwell
      differences, nm^2/s^2), ``min_time`` and ``min_time_tolerance`` (relative).
    * solver: ``solver`` (``"auto"``, ``"qp"``, ``"first-order"``), ``operator`` (``"auto"``,
      ``"sparse"``, ``"fft"``, ``"stencil"``, ``"nufft"``, ``"fft-spread"``), ``first_order_method`` (``"lbfgs"``, the default,
      ``"fista"``, ``"newton-cg"``), ``lbfgs_memory`` (the L-BFGS's correction pairs, 1 to 100,
      default 10, 5 with the FFT operator, as ``--lbfgs-memory``),
      ``tolerance`` (relative; both solvers), ``max_iterations``, ``warm_start`` (a previous
      dwell.csv).
    * the tool's calibration: ``calibration`` (``calibration.json`` of :func:`calibrate` or
      ``preston calibrate``): the plan includes the calibrated drift, ``report["expected_rms_nm"]``
      draws from the calibration's uncertainty, and its calibrated TIF (``tif.csv`` beside it)
      is the TIF unless one is given.
    * curved parts: ``surface`` (design surface JSON) and ``tif_frame`` (``"path_tangent"``,
      ``"machine_x"``).
    * the plan's model: ``influence`` (``"swept"``, the default, or ``"point"``), ``robust``
      (plan for the mean over the TIF-uncertainty scenarios), ``spread_tolerance``; a Hertzian
      tool: ``hertz`` (a dict with the keys of a job's ``[tif.hertz]``), ``tif_pitch_mm``,
      ``curvature_dependent``.
    * edges: ``edge`` (``"none"``, ``"zero-band"``, ``"gaussian"``, ``"polynomial"``,
      ``"gerchberg-papoulis"``: how the map is extended into the dwell area beyond it) and
      ``edge_width_mm`` (the band's width, mm), as ``--edge`` / ``[edge]``.

    ``progress(event)`` is called during the work with a dict: ``stage`` (``"assembly"``,
    ``"solve"``, ``"loop"``), ``event`` (``"start"``, ``"advance"``, ``"finish"``,
    ``"iteration"``), ``done`` and ``total`` (units of the stage), and for iterations
    ``iteration``, ``objective`` (nm^2) and ``kkt_residual``. An exception raised by the callback
    is raised by :func:`solve` once the engine returns.

    ``threads`` bounds the threads the engine uses for this call (default: the process's pool,
    ``RAYON_NUM_THREADS`` or one per core); the results are the same for every thread count.
    Give ``threads=1`` when several solves run at once on one machine (threads or processes).

    The interpreter is released while the engine runs. A solver that stops before converging is
    a status (``result.converged`` is False), not an error, unless ``require_converged=True``
    (then :class:`NotConvergedError`).
    """
    j, name, arrays = _job_of(
        job,
        map_xyz=map_xyz,
        map_options=map_options,
        tif_xyr=tif_xyr,
        dwell_xy=dwell_xy,
        **overrides,
    )
    native = _preston.solve(_dumps(j), name, progress=progress, threads=threads, **arrays)
    result = SolveResult(native)
    if require_converged and not result.converged:
        raise NotConvergedError(
            f"{name}: the solver stopped before converging (status {result.status}, "
            f"{result.report.get('iterations')} iterations)"
        )
    return result


def sample_job(dir: PathLike, overwrite: bool = False) -> Path:
    """Writes the sample job into ``dir`` (created if missing) and returns its job file: the job
    of the repository's ``data/job.toml`` (a 118 x 8 mm mirror's error map, a measured fluid-jet
    TIF, both embedded in the package), its CSV files named relative to the job, and README.md
    with the data's source and licence. ``preston.solve(preston.sample_job("sample"))`` solves it
    without a checkout of the sources; ``preston sample --out DIR`` writes the same files.

    The files are renamed into place together (all or none). A file of the sample that exists in
    ``dir`` already is an :class:`InputError` naming it, and nothing is written, unless
    ``overwrite=True``."""
    return Path(_preston.sample_job(os.fspath(dir), overwrite))


def _map_options(options: Mapping[str, Any]) -> dict:
    out = dict(options)
    if isinstance(out.get("remove"), str):
        out["remove"] = [t.strip() for t in out["remove"].split(",") if t.strip()]
    if isinstance(out.get("aperture"), str) and out["aperture"].startswith("polygon:"):
        out["aperture"] = "polygon:" + _abs(out["aperture"][len("polygon:") :].strip())
    return out


def read_map(path: PathLike, **format_options: Any) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reads a measured map, returning ``(x_mm, y_mm, z_nm)`` (float64 arrays of the kept points).

    Every format of the CLI: CSV with units in the header (``x_mm,y_mm,z_nm``; ``x_um``,
    ``z_um``, ... converted), XYZ text, NumPy ``.npy`` (needs ``pitch_mm``), Zygo ``.dat`` and
    ``.datx``, 4D ``.h5``/``.4D``. ``format_options`` are those of a job's ``[map]``:

    * ``format`` -- ``"csv"``, ``"xyz"``, ``"npy"``, ``"zygo-dat"``, ``"zygo-datx"``,
      ``"four-d"`` (default: from the extension).
    * ``columns`` -- column order of a text map, e.g. ``"z,x,y"`` (``_`` skips a column).
    * ``units`` -- units of x, y, z of a text map (``"mm,mm,um"``; m, mm, um, nm).
    * ``pitch_mm`` -- pixel pitch of a ``.npy`` grid (or a 4D file without one), mm.
    * ``aperture`` -- ``"circle:R[@x,y]"``, ``"annulus:R1,R2"``, ``"rect:W,H"``,
      ``"polygon:FILE"`` (mm); points outside are dropped.
    * ``remove`` -- form terms removed by least squares: a list or ``"piston,tilt,power"``.

    Invalid pixels (NaN, no-data) are dropped. Gridded files are centred on the origin with the
    first stored row at the top (largest y).
    """
    unknown = sorted(set(format_options) - set(MAP_OPTIONS))
    if unknown:
        raise InputError(f"read_map: unknown options {unknown} (known: {', '.join(MAP_OPTIONS)})")
    source = {"file": _abs(path), **_map_options(format_options)}
    x, y, z, _how = _preston.read_map(_dumps(source))
    return x, y, z


def simulate(
    map_xyz: ArrayLike,
    dwell_xy: ArrayLike,
    dwell_s: ArrayLike,
    *,
    tif: Optional[PathLike] = None,
    tif_xyr: Optional[ArrayLike] = None,
    gaussian: Optional[Mapping[str, float]] = None,
    samples_per_point: Optional[int] = None,
    progress: Optional[Callable[[dict], Any]] = None,
) -> Tuple[np.ndarray, np.ndarray]:
    """The removal a dwell program produces: ``(removal_nm, residual_nm)`` at the map points.

    ``map_xyz``: ``(N, 3)`` (x_mm, y_mm, z_nm) or ``(x, y, z)``; ``dwell_xy``: ``(M, 2)`` dwell
    points in path order, mm; ``dwell_s``: ``(M,)`` dwell times, s. The TIF is one of ``tif``
    (CSV file), ``tif_xyr`` (``(K, 3)`` grid samples, rate nm/s) or ``gaussian``. Discrete dwells
    (the solver's model, ``h = R t``) unless ``samples_per_point`` is given: then the tool sweeps
    the path at the scheduled feeds, integrated with that many midpoint samples per dwell point.
    ``residual_nm`` is ``z - removal`` with its mean removed (as :func:`solve` reports it)."""
    m = _columns(map_xyz, 3, "map_xyz")
    pts = _columns(dwell_xy, 2, "dwell_xy")
    t = np.ascontiguousarray(dwell_s, dtype=np.float64)
    if t.ndim != 1:
        raise InputError(f"dwell_s: expected a 1-D array, got shape {t.shape}")
    if sum(x is not None for x in (tif, tif_xyr, gaussian)) != 1:
        raise InputError("give one of tif=, tif_xyr=, gaussian=")
    g = _gaussian(gaussian) if gaussian is not None else None
    tif_json = _dumps({"file": _abs(tif) if tif is not None else None, "gaussian": g})
    xyr = _columns(tif_xyr, 3, "tif_xyr") if tif_xyr is not None else None
    removal = _preston.simulate(
        np.ascontiguousarray(m[:, :2]), pts, t, tif_json, xyr, samples_per_point, progress
    )
    e = m[:, 2] - removal
    return removal, e - e.mean()


def raster(
    x_range_mm: Tuple[float, float],
    y_range_mm: Tuple[float, float],
    pitch_mm: float,
    along: str = "x",
) -> Tuple[np.ndarray, np.ndarray]:
    """A serpentine raster (the one ``raster_pitch_mm`` generates) over the box
    ``x_range_mm`` x ``y_range_mm`` at ``pitch_mm``, lines along ``"x"`` or ``"y"``:
    ``(x_mm, y_mm)`` in path order."""
    (x0, x1), (y0, y1) = x_range_mm, y_range_mm
    return _preston.raster(float(x0), float(x1), float(y0), float(y1), float(pitch_mm), along)


def fit(
    points_xyz: ArrayLike,
    order: int = 10,
    *,
    norm_radius_mm: Optional[float] = None,
    curvature_per_mm: float = 0.0,
    conic: float = 0.0,
    fit_conic: bool = False,
) -> Tuple[dict, dict, np.ndarray]:
    """Least-squares XY-polynomial surface (``preston fit``) through points ``(N, 3)`` or
    ``(x, y, z)``, all in mm, on a conic base of vertex curvature ``curvature_per_mm`` (1/mm) and
    ``conic`` constant (or both fitted with ``fit_conic=True``), polynomial of total ``order``
    normalised by ``norm_radius_mm`` (default: the largest radius of the points).

    Returns ``(surface, summary, residual_nm)``: the surface as the dict ``preston fit --out``
    writes (save it with ``json.dump`` for ``solve(surface=...)``), the summary (``rms_nm``,
    ``pv_nm``, ``condition_number``, ``points``, ...) and the residual at each point, nm."""
    pts = _columns(points_xyz, 3, "points_xyz")
    surface, summary, residual = _preston.fit(
        pts, int(order), norm_radius_mm, float(curvature_per_mm), float(conic), bool(fit_conic)
    )
    return json.loads(surface), json.loads(summary), residual


def nc(
    dwell_xy: ArrayLike,
    dwell_s: ArrayLike,
    *,
    surface: Optional[PathLike] = None,
    notes: Sequence[str] = (),
    out: Optional[PathLike] = None,
    **settings: Any,
) -> str:
    """The G-code program of ``preston nc`` for a dwell plan, as text.

    ``dwell_xy``: ``(N, 2)`` dwell points in path order, mm; ``dwell_s``: ``(N,)`` dwell times, s
    (e.g. ``np.column_stack([r.dwell_x_mm, r.dwell_y_mm])`` and ``r.dwell_s`` of :func:`solve`).
    ``surface``: design surface JSON (default: a flat part, Z = 0). ``notes``: comment lines
    of the header. ``settings`` are the keys of the NC settings: ``v_max_mm_per_min``,
    ``a_max_mm_per_s2``, ``corner_angle_deg``, ``tool_radius_mm``, ``tool_axis``, ``dialect``
    (``"iso"``, ``"sinumerik"``, ...), ``feed_mode``, ``clearance_mm``,
    ``plunge_feed_mm_per_min``, ``min_block_time_ms``, ``spindle_rpm``, ``coolant``,
    ``compensation``. The program is read back and checked against the plan before it is
    returned; a plan no program can deliver raises :class:`InputError` naming the point. With
    ``out`` the program is also written to that file (whole or not at all), as ``preston nc
    --out``; :func:`simulate_program` takes either the text or the file."""
    pts = _columns(dwell_xy, 2, "dwell_xy")
    t = np.ascontiguousarray(dwell_s, dtype=np.float64)
    if t.ndim != 1:
        raise InputError(f"dwell_s: expected a 1-D array, got shape {t.shape}")
    text, _blocks = _preston.nc(
        pts, t, _dumps(settings), _abs(surface) if surface is not None else None, list(notes)
    )
    if out is not None:
        _write_text_atomic(os.fspath(out), text)
    return text


def _write_text_atomic(path: str, text: str) -> None:
    """Writes ``text`` to ``path`` through a temporary file in its directory, renamed into place."""
    import tempfile

    directory = os.path.dirname(os.path.abspath(path))
    try:
        fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", dir=directory)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except OSError as e:
        raise InputFileError(f"{path}: {e.strerror or e}") from None


from ._batch import batch, grid  # noqa: E402  (needs the names above)
from ._shop import calibrate, shop  # noqa: E402
from ._paths import (  # noqa: E402
    ToolPath,
    path_chord_height,
    path_intersection,
    path_project,
    path_raster,
)
from ._workflow import (  # noqa: E402
    iterate,
    path_edge_offset,
    path_random,
    path_spiral,
    register,
    simulate_program,
    tif_bonnet,
    tif_gaussian,
    tif_grid,
    tif_hertz,
    tif_spot,
)
