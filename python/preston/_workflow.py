"""TIF models and measured grids, tool paths, registration and program simulation: the rest of
the CLI's workflow (``preston tif``, ``preston path``, ``preston register``, ``preston simulate
--program``), numpy arrays in and out. Units: lengths mm, heights nm, rates nm/s, times s."""

from __future__ import annotations

import json
import os
from typing import Any, Callable, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from . import _preston
from ._preston import InputError

PathLike = Union[str, "os.PathLike[str]"]
ArrayLike = Any
Tif = Tuple[np.ndarray, dict]

_DOFS = ("rx", "ry", "rz", "tx", "ty", "tz")


def _dumps(obj: Any) -> str:
    from . import _dumps as dumps

    return dumps(obj)


def _columns(a: ArrayLike, k: int, name: str) -> np.ndarray:
    from . import _columns as columns

    return columns(a, k, name)


def _xyr(x: np.ndarray, y: np.ndarray, r: np.ndarray, summary: str) -> Tif:
    return np.column_stack([x, y, r]), json.loads(summary)


def _surface_json(surface: Union[PathLike, Mapping[str, Any]]) -> str:
    """A design surface (a JSON file, or the dict :func:`preston.fit` returns) as JSON text."""
    if isinstance(surface, Mapping):
        return _dumps(surface)
    path = os.fspath(surface)
    try:
        with open(path, encoding="utf-8") as f:
            return f.read()
    except OSError as e:
        raise InputError(f"{path}: cannot read the surface file ({e.strerror})") from None


def tif_gaussian(
    sigma_mm: float, peak_nm_per_s: float, pitch_mm: float, truncation_mm: Optional[float] = None
) -> Tif:
    """A truncated Gaussian TIF ``r = peak exp(-rho^2 / (2 sigma^2))`` for ``rho <= truncation``
    (default 3 sigma) sampled on a grid of ``pitch_mm`` (``preston tif gaussian``).

    Returns ``(tif_xyr, summary)``: the ``(N, 3)`` grid samples x_mm, y_mm, rate_nm_per_s (row-
    major, ready for ``solve(tif_xyr=...)``) and the dict ``preston tif`` prints (``peak_rate_nm_per_s``,
    ``volume_rate_mm3_per_min`` of the model, ``grid_volume_rate_mm3_per_min``, ``fwhm_mm``,
    ``nx``, ``ny``, ``pitch_mm``, ...)."""
    params = {
        "sigma_mm": float(sigma_mm),
        "peak_rate_nm_per_s": float(peak_nm_per_s),
        "truncation_radius_mm": float(truncation_mm if truncation_mm is not None else 3.0 * sigma_mm),
    }
    return _xyr(*_preston.tif_model("gaussian", _dumps(params), float(pitch_mm)))


def tif_hertz(
    *,
    tool_e_gpa: float,
    tool_nu: float,
    part_e_gpa: float,
    part_nu: float,
    preston_k: float,
    pitch_mm: float,
    force_n: float = 10.0,
    tool_radius_mm: float = 16.0,
    spindle_rad_s: float = 104.72,
    tilt_deg: float = 15.0,
    part_radius_mm: Optional[float] = None,
    surface: Optional[Union[PathLike, Mapping[str, Any]]] = None,
    at_mm: Optional[Tuple[float, float]] = None,
) -> Tif:
    """The TIF of a spherical tool in Hertzian contact spinning about an axis tilted by
    ``tilt_deg`` (``preston tif hertz``): Preston's law ``rate = K p v`` with the Hertz pressure
    ``p`` (force N, moduli GPa, radii mm) and the sliding speed ``v`` (spindle rad/s); ``preston_k``
    in mm^2/N. The part is flat, a sphere of ``part_radius_mm`` (positive convex, negative
    concave), or the design ``surface`` (file or dict) at ``at_mm`` = (x, y) mm.

    Returns ``(tif_xyr, summary)`` as :func:`tif_gaussian`; the summary adds
    ``contact_radius_mm``, ``peak_pressure_mpa``, ``centre_speed_mm_per_s`` and
    ``effective_radius_mm``."""
    if (surface is None) != (at_mm is None):
        raise InputError("tif_hertz: give surface= with at_mm=(x, y)")
    params = {
        "force_n": force_n,
        "tool_radius_mm": tool_radius_mm,
        "spindle_rad_s": spindle_rad_s,
        "tilt_deg": tilt_deg,
        "tool_e_gpa": tool_e_gpa,
        "tool_nu": tool_nu,
        "part_e_gpa": part_e_gpa,
        "part_nu": part_nu,
        "preston_k_mm2_per_n": preston_k,
    }
    return _xyr(
        *_preston.tif_model(
            "hertz",
            _dumps(params),
            float(pitch_mm),
            part_radius_mm,
            _surface_json(surface) if surface is not None else None,
            tuple(float(v) for v in at_mm) if at_mm is not None else None,
        )
    )


def tif_bonnet(
    *,
    bonnet_radius_mm: float,
    depth_mm: float,
    force_n: float,
    preston_k: float,
    pitch_mm: float,
    precession_deg: float = 20.0,
    azimuths: int = 1,
    spindle_rad_s: float = 104.72,
) -> Tif:
    """The TIF of a bonnet pressed by ``depth_mm`` and precessed by ``precession_deg`` (averaged
    over ``azimuths`` precession positions), ``preston tif bonnet``: ``rate = K p v`` with
    ``preston_k`` in mm^2/N, force N, spindle rad/s.

    Returns ``(tif_xyr, summary)`` as :func:`tif_hertz`."""
    params = {
        "bonnet_radius_mm": bonnet_radius_mm,
        "depth_mm": depth_mm,
        "precession_deg": precession_deg,
        "precession_azimuths": int(azimuths),
        "spindle_rad_s": spindle_rad_s,
        "force_n": force_n,
        "preston_k_mm2_per_n": preston_k,
    }
    return _xyr(*_preston.tif_model("bonnet", _dumps(params), float(pitch_mm)))


def tif_grid(
    tif_xyr: ArrayLike,
    *,
    pitch_mm: Optional[float] = None,
    recentre: bool = False,
    peak_nm_per_s: Optional[float] = None,
    volume_mm3_per_min: Optional[float] = None,
) -> Tif:
    """A measured TIF grid (``(N, 3)`` x_mm, y_mm, rate_nm_per_s, e.g. ``np.loadtxt`` of a TIF
    CSV) resampled bilinearly to ``pitch_mm``, moved so that its rate-weighted centroid is the
    origin (``recentre``), and scaled to a peak rate (nm/s) or a volumetric rate (mm^3/min), in
    that order (``preston tif grid``). Returns ``(tif_xyr, summary)``."""
    return _xyr(
        *_preston.tif_grid(
            _columns(tif_xyr, 3, "tif_xyr"), pitch_mm, bool(recentre), peak_nm_per_s, volume_mm3_per_min
        )
    )


def tif_spot(
    before_xyz: ArrayLike,
    after_xyz: ArrayLike,
    dwell_s: float,
    *,
    crop_radius_mm: Optional[float] = None,
    remove_tilt: bool = False,
    recentre: bool = False,
    fit: Optional[str] = None,
) -> Tif:
    """A measured TIF from maps before and after a stationary dwell of ``dwell_s`` s (``preston
    tif spot``): ``(before - after) / dwell_s`` in nm/s on the maps' common grid, the background
    (piston, and tilt with ``remove_tilt``) fitted outside ``crop_radius_mm`` (default 0.4 of the
    grid's smaller side) and removed, zero outside it. ``before_xyz`` / ``after_xyz`` are ``(N, 3)``
    arrays or the tuples :func:`preston.read_map` returns. ``fit="gaussian"`` adds an elliptical
    Gaussian fit (``sigma_x_mm``, ``sigma_y_mm``, ``gaussian_peak_nm_per_s``,
    ``gaussian_centre_mm``) to the summary. Returns ``(tif_xyr, summary)``."""
    if fit not in (None, "gaussian"):
        raise InputError(f"tif_spot: fit must be None or 'gaussian', got {fit!r}")
    return _xyr(
        *_preston.tif_spot(
            _columns(before_xyz, 3, "before_xyz"),
            _columns(after_xyz, 3, "after_xyz"),
            float(dwell_s),
            crop_radius_mm,
            bool(remove_tilt),
            bool(recentre),
            fit == "gaussian",
        )
    )


def path_spiral(
    radius_mm: float,
    pitch_mm: float,
    step_mm: Optional[float] = None,
    centre_mm: Tuple[float, float] = (0.0, 0.0),
) -> Tuple[np.ndarray, np.ndarray]:
    """An Archimedes spiral ``r = pitch theta / (2 pi)`` from ``centre_mm`` out to ``radius_mm``,
    points about ``step_mm`` (default: the pitch) apart along the curve (``preston path spiral``):
    ``(x_mm, y_mm)`` in path order, ready for ``solve(dwell_xy=...)``."""
    c = (float(centre_mm[0]), float(centre_mm[1]))
    return _preston.path_spiral(c, float(radius_mm), float(pitch_mm), float(step_mm if step_mm is not None else pitch_mm))


def path_random(
    x_range_mm: Tuple[float, float],
    y_range_mm: Tuple[float, float],
    pitch_mm: float,
    *,
    seed: int = 1,
    max_run: int = 20,
    jitter: float = 0.0,
) -> Tuple[np.ndarray, np.ndarray, dict]:
    """A pseudo-random unicursal path (``preston path random``): every node of the grid of
    ``pitch_mm`` over the box visited once in one stroke, straight runs of at most ``max_run``
    steps, nodes moved by uniform offsets of up to ``jitter * pitch / 2`` (``jitter`` in [0, 1]).
    Returns ``(x_mm, y_mm, summary)``; the summary has the CLI's keys (``nodes``,
    ``longest_run``, ``tree_exchanges``, ...)."""
    settings = {"pitch_mm": float(pitch_mm), "seed": int(seed), "max_run": int(max_run), "jitter": float(jitter)}
    (x0, x1), (y0, y1) = x_range_mm, y_range_mm
    x, y, summary = _preston.path_random((float(x0), float(x1)), (float(y0), float(y1)), _dumps(settings))
    return x, y, json.loads(summary)


def path_edge_offset(
    *,
    bonnet_radius_mm: float,
    spot_max_mm: float,
    spot_min_mm: float,
    residual_um: float,
    edge_xy: Optional[ArrayLike] = None,
    edge_radius_mm: Optional[float] = None,
    ratio: Optional[float] = None,
    decrement_mm: Optional[float] = None,
    overhang_mm: float = 0.0,
    bezier_tol_mm: float = 0.01,
    step_mm: float = 0.5,
) -> Tuple[np.ndarray, np.ndarray, dict]:
    """The lifting-bonnet edge-offset trajectory (``preston path edge-offset``) inside a closed
    edge: ``edge_xy`` (``(N, 2)`` polygon, mm) or a circle of ``edge_radius_mm``. Spot radii
    shrink from ``spot_max_mm`` to ``spot_min_mm`` geometrically (``ratio``) or arithmetically
    (``decrement_mm``); lines are spaced for a scallop of ``residual_um``. Returns ``(x_mm, y_mm,
    summary)`` with the CLI's summary keys (``lines``, ``line_starts``, ``corners``, ...)."""
    if (edge_xy is None) == (edge_radius_mm is None):
        raise InputError("path_edge_offset: give edge_xy= or edge_radius_mm=")
    if (ratio is None) == (decrement_mm is None):
        raise InputError("path_edge_offset: give ratio= or decrement_mm=")
    if edge_xy is not None:
        edge = _columns(edge_xy, 2, "edge_xy")
    else:
        r = float(edge_radius_mm)  # type: ignore[arg-type]
        if not (np.isfinite(r) and r > 0.0):
            raise InputError(f"path_edge_offset: edge_radius_mm must be positive, got {r}")
        # The CLI's circle: 720 vertices, 0.5 degrees apart.
        t = np.radians(np.arange(720) * 0.5)
        edge = np.column_stack([r * np.cos(t), r * np.sin(t)])
    progression = (
        {"type": "geometric", "ratio": float(ratio)}
        if ratio is not None
        else {"type": "arithmetic", "decrement_mm": float(decrement_mm)}  # type: ignore[arg-type]
    )
    settings = {
        "bonnet_radius_mm": bonnet_radius_mm,
        "spot_max_mm": spot_max_mm,
        "spot_min_mm": spot_min_mm,
        "progression": progression,
        "residual_height_mm": residual_um * 1e-3,
        "overhang_mm": overhang_mm,
        "bezier_tolerance_mm": bezier_tol_mm,
        "step_mm": step_mm,
    }
    x, y, summary = _preston.path_edge_offset(edge, _dumps(settings))
    return x, y, json.loads(summary)


def register(
    surface: Union[PathLike, Mapping[str, Any]],
    points_xyz: ArrayLike,
    *,
    probe_radius_mm: float = 0.0,
    robust: str = "none",
    huber_k: float = 1.345,
    max_iterations: int = 50,
    lock: Sequence[str] = (),
    max_rotation_arcsec: Optional[float] = None,
    max_translation_um: Optional[float] = None,
    installation_range_mm: float = 0.5,
    installation_range_deg: float = 0.2,
) -> dict:
    """Installation error (ICP) and form error of measured points on a design surface
    (``preston register``): the rigid transform ``M`` with ``p_design = M p_measured`` by
    Gauss-Newton, optionally Huber-weighted (``robust="huber"``, threshold ``huber_k`` robust
    standard deviations), with DOFs held at zero (``lock``: names among rx, ry, rz, tx, ty, tz),
    prior bounds (arcsec, um) and contact-probe compensation (``probe_radius_mm``: the points are
    tip centres). A motion whose standard deviation (from the residual's scatter) exceeds the
    installation range along it (``installation_range_mm``, ``installation_range_deg``) is held
    and listed in ``transform["locked"]`` with its reason.

    ``surface``: a surface JSON file or the dict :func:`preston.fit` returns. ``points_xyz``:
    ``(N, 3)`` or ``(x, y, z)``, all in mm. Motions the points and the surface leave undetermined
    raise :class:`InputError` (hold them with ``lock``); stopping at the iteration limit is
    ``transform["converged"] == False``, not an error.

    Returns a dict: ``transform`` (the content of transform.json: ``matrix``,
    ``rotation_arcsec``, ``translation_um``, ``rms_nm``, ``dof_sigma``, ``locked``, ...),
    ``design_x_mm``, ``design_y_mm``, ``form_error_nm`` (form_error.csv: the foot of each point on
    the design and its signed normal deviation, nm), ``points_xyz_mm`` (``(N, 3)`` registered
    points) and ``weights`` (registered_points.csv)."""
    unknown = [d for d in lock if d not in _DOFS]
    if unknown:
        raise InputError(f"register: unknown DOFs {unknown} in lock (known: {', '.join(_DOFS)})")
    if robust == "none":
        rob: dict = {"kind": "none"}
    elif robust == "huber":
        rob = {"kind": "huber", "k": float(huber_k)}
    else:
        raise InputError(f"register: robust must be 'none' or 'huber', got {robust!r}")
    settings = {
        "max_iterations": int(max_iterations),
        "robust": rob,
        "probe_radius_mm": float(probe_radius_mm),
        "lock": [d in lock for d in _DOFS],
        "installation_range_mm": float(installation_range_mm),
        "installation_range_deg": float(installation_range_deg),
        "max_rotation_arcsec": max_rotation_arcsec,
        "max_translation_um": max_translation_um,
    }
    tf, fx, fy, fe, pts, w = _preston.register(
        _surface_json(surface), _columns(points_xyz, 3, "points_xyz"), _dumps(settings)
    )
    return {
        "transform": json.loads(tf),
        "design_x_mm": fx,
        "design_y_mm": fy,
        "form_error_nm": fe,
        "points_xyz_mm": pts.reshape(-1, 3),
        "weights": w,
    }


def simulate_program(
    map: PathLike,
    program: Union[PathLike, str],
    *,
    tif: Optional[PathLike] = None,
    tif_xyr: Optional[ArrayLike] = None,
    gaussian: Optional[Mapping[str, float]] = None,
    a_max_mm_per_s2: Optional[float] = None,
    corner_angle_deg: float = 60.0,
    dialect: Optional[str] = None,
    sample_step_mm: Optional[float] = None,
    surface: Optional[Union[PathLike, Mapping[str, Any]]] = None,
    tool_radius_mm: float = 0.0,
    tif_frame: str = "path_tangent",
    map_options: Optional[Mapping[str, Any]] = None,
    progress: Optional[Callable[[dict], Any]] = None,
) -> dict:
    """The removal a G-code program produces as the machine runs it (``preston simulate
    --program``): the program (a file, e.g. from ``preston nc``, or the text :func:`preston.nc`
    returns: a string holding a newline is taken as the program's text) read back in
    its ``dialect`` (default: the one its header names), executed at the programmed feed or, with
    ``a_max_mm_per_s2`` (mm/s^2), with acceleration-limited look-ahead stopping at turns above
    ``corner_angle_deg``; the TIF (``tif`` file, ``tif_xyr`` grid samples or ``gaussian``)
    integrated along the contact motion in samples of at most ``sample_step_mm`` (default 1/64 of
    the TIF radius) on the map file (read with ``map_options``, those of :func:`preston.read_map`).
    On a curved part give its ``surface`` and the ``tool_radius_mm`` the program's tool centres
    are offset by: each contact sample then applies the TIF in its tangent plane, its x axis
    along the motion (``tif_frame="path_tangent"``) or the machine x axis projected
    (``"machine_x"``), as ``preston solve`` plans it.

    Returns a dict: ``map_x_mm``, ``map_y_mm``, ``z_nm``, ``removal_nm``, ``residual_nm`` (``z -
    removal`` with its mean removed), ``report`` (report.json keys) and ``check`` (executed
    against planned dwell over the marked stretches: ``stretches``, ``planned_total_s``,
    ``executed_total_s``, ``max_relative_error``, ``worst_point``, ``over_5_percent``,
    ``executed_time_s``, ``samples``)."""
    from . import MAP_OPTIONS, _abs, _gaussian, _map_options

    if isinstance(program, str) and "\n" in program:
        import tempfile

        with tempfile.TemporaryDirectory(prefix="preston-") as d:
            path = os.path.join(d, "program.nc")
            with open(path, "w", encoding="utf-8") as f:
                f.write(program)
            return simulate_program(
                map,
                path,
                tif=tif,
                tif_xyr=tif_xyr,
                gaussian=gaussian,
                a_max_mm_per_s2=a_max_mm_per_s2,
                corner_angle_deg=corner_angle_deg,
                dialect=dialect,
                sample_step_mm=sample_step_mm,
                surface=surface,
                tool_radius_mm=tool_radius_mm,
                tif_frame=tif_frame,
                map_options=map_options,
                progress=progress,
            )
    if sum(x is not None for x in (tif, tif_xyr, gaussian)) != 1:
        raise InputError("give one of tif=, tif_xyr=, gaussian=")
    if gaussian is not None:
        gaussian = _gaussian(gaussian)
    opts = dict(map_options or {})
    unknown = sorted(set(opts) - set(MAP_OPTIONS))
    if unknown:
        raise InputError(f"map_options: unknown {unknown} (known: {', '.join(MAP_OPTIONS)})")
    source = {"file": _abs(map), **_map_options(opts)}
    tif_json = _dumps({"file": _abs(tif) if tif is not None else None, "gaussian": gaussian})
    xyr = _columns(tif_xyr, 3, "tif_xyr") if tif_xyr is not None else None
    x, y, z, removal, residual, report, check = _preston.simulate_program(
        _dumps(source),
        _abs(program),
        tif_json,
        xyr,
        a_max_mm_per_s2,
        float(corner_angle_deg),
        dialect,
        sample_step_mm,
        _surface_json(surface) if surface is not None else None,
        float(tool_radius_mm),
        tif_frame,
        progress,
    )
    return {
        "map_x_mm": x,
        "map_y_mm": y,
        "z_nm": z,
        "removal_nm": removal,
        "residual_nm": residual,
        "report": json.loads(report),
        "check": json.loads(check),
    }


def iterate(
    *,
    tif: Optional[PathLike] = None,
    tif_xyr: Optional[ArrayLike] = None,
    gaussian: Optional[Mapping[str, float]] = None,
    surface: Optional[Union[PathLike, Mapping[str, Any]]] = None,
    map_xyz: Optional[ArrayLike] = None,
    iteration: int = 0,
    aperture_x_mm: Tuple[float, float] = (-25.0, 25.0),
    aperture_y_mm: Tuple[float, float] = (-25.0, 25.0),
    grid: Tuple[int, int] = (51, 51),
    pitch_mm: float = 1.0,
    margin_mm: Optional[float] = None,
    v_max: float = 3000.0,
    v_min: float = 0.0,
    rho: float = 0.01,
    lambda_: float = 0.0,
    tolerance: float = 1e-4,
    solver: str = "auto",
    iterations: int = 5,
    spec_rms_nm: float = 0.0,
    spec_pv_nm: float = 0.0,
    form_error_rms_nm: float = 100.0,
    form_error_cycles: float = 2.0,
    form_error_seed: int = 1,
    rotation_arcsec: Sequence[float] = (0.0, 0.0, 0.0),
    translation_um: Sequence[float] = (0.0, 0.0, 0.0),
    noise_nm: float = 0.0,
    tif_rate_error: float = 0.0,
    positioning_noise_mm: float = 0.0,
    seed: int = 7,
    installation_range_mm: float = 0.5,
    installation_range_deg: float = 0.2,
    progress: Optional[Callable[[dict], Any]] = None,
    threads: Optional[int] = None,
) -> dict:
    """The measure-register-solve-polish loop (``preston iterate``; the same defaults).

    A virtual part: the design ``surface`` (file or dict; default the plane z = 0) with a generated
    smooth form error (``form_error_rms_nm`` nm RMS, at most ``form_error_cycles`` cycles across the
    aperture), installed with an error (``rotation_arcsec``, ``translation_um``), measured on a
    ``grid`` over the aperture (mm) with ``noise_nm`` of noise, registered (ICP), solved for dwell
    on an intersection raster of ``pitch_mm`` (feeds ``v_min``..``v_max`` mm/min, weights ``rho``
    nm^2/s and ``lambda_`` nm^2/s^2, ``solver`` at ``tolerance``) and polished with a TIF rate
    error up to ``tif_rate_error`` (relative) and ``positioning_noise_mm``; ``iterations`` runs at
    most, stopping at ``spec_rms_nm`` / ``spec_pv_nm``. With ``map_xyz`` (a real part's measured
    error, ``(N, 3)`` mm, mm, nm): one planned run ``iteration`` on it.

    Returns a dict: ``records`` (one dict per measurement, the columns of convergence.csv:
    ``iteration``, ``pv_nm``, ``rms_nm``, ``max_abs_nm``, ``mean_abs_nm``, ``time_s``,
    ``predicted_rms_nm``, ``tif_rate_error``), ``met_spec``, ``not_converged`` (inner steps that
    stopped early: the CLI's exit 3), ``final_measured`` (``(x_mm, y_mm, z_nm)``) and
    ``last_run`` (``None`` or a dict ``dwell_x_mm``, ``dwell_y_mm``, ``dwell_s``, ``measured``)."""
    from . import _abs

    if sum(x is not None for x in (tif, tif_xyr, gaussian)) != 1:
        raise InputError("give one of tif=, tif_xyr=, gaussian=")
    if solver not in ("auto", "qp", "first-order"):
        raise InputError(f"iterate: solver must be 'auto', 'qp' or 'first-order', got {solver!r}")
    (x0, x1), (y0, y1) = aperture_x_mm, aperture_y_mm
    settings = {
        "aperture": {"x_min_mm": x0, "x_max_mm": x1, "y_min_mm": y0, "y_max_mm": y1},
        "grid": [int(grid[0]), int(grid[1])],
        "path_pitch_mm": pitch_mm,
        "path_margin_mm": margin_mm,
        "feed": {"v_max_mm_per_min": v_max, "v_min_mm_per_min": v_min},
        "max_iterations": int(iterations),
        "spec_rms_nm": spec_rms_nm,
        "spec_pv_nm": spec_pv_nm,
        "rho": rho,
        "lambda": lambda_,
        "disturbances": {"tif_rate_error": tif_rate_error, "positioning_noise_mm": positioning_noise_mm},
        "seed": int(seed),
        "register": {
            "installation_range_mm": float(installation_range_mm),
            "installation_range_deg": float(installation_range_deg),
        },
        "solver": {"tolerance": tolerance, "first_order_tolerance": tolerance, "solver": solver},
    }
    if len(rotation_arcsec) != 3 or len(translation_um) != 3:
        raise InputError("iterate: rotation_arcsec and translation_um take three values (x, y, z)")
    part = {
        "form_error": {"rms_nm": form_error_rms_nm, "max_cycles": form_error_cycles, "seed": int(form_error_seed)},
        "rotation_arcsec": [float(v) for v in rotation_arcsec],
        "translation_um": [float(v) for v in translation_um],
        "measurement_noise_nm": noise_nm,
    }
    tif_json = _dumps({"file": _abs(tif) if tif is not None else None, "gaussian": gaussian})
    xyr = _columns(tif_xyr, 3, "tif_xyr") if tif_xyr is not None else None
    text, fx, fy, fz, last = _preston.iterate(
        _dumps(settings),
        _surface_json(surface) if surface is not None else None,
        tif_json,
        xyr,
        _dumps(part),
        _columns(map_xyz, 3, "map_xyz") if map_xyz is not None else None,
        int(iteration),
        progress,
        threads,
    )
    out = json.loads(text)
    out["final_measured"] = (fx, fy, fz)
    out["last_run"] = (
        None
        if last is None
        else {"dwell_x_mm": last[0], "dwell_y_mm": last[1], "dwell_s": last[2], "measured": last[3:]}
    )
    return out
