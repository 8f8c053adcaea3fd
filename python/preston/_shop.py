"""The shop loop: the tool that ran learned from a run's measured change (``preston calibrate``)
and the virtual shop that rehearses the loop (``preston shop``). Units: lengths mm, heights nm,
rates nm/s, times s."""

from __future__ import annotations

import json
import os
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np

from . import _preston
from ._preston import InputError, NotConvergedError

PathLike = Union[str, "os.PathLike[str]"]
ArrayLike = Any

#: What ``model=`` of :func:`calibrate` fits, as ``preston calibrate --model``.
MODELS = ("full", "shape", "basic")


def _tif_arguments(
    tif: Optional[PathLike], tif_xyr: Optional[ArrayLike], gaussian: Optional[Mapping[str, float]]
) -> tuple:
    """The spot test as the native functions take it: ``(tif_json, tif_xyr)``."""
    from . import _abs, _columns, _dumps, _gaussian

    if sum(x is not None for x in (tif, tif_xyr, gaussian)) != 1:
        raise InputError("give one of tif=, tif_xyr=, gaussian=")
    g = _gaussian(gaussian) if gaussian is not None else None
    tif_json = _dumps({"file": _abs(tif) if tif is not None else None, "gaussian": g})
    xyr = _columns(tif_xyr, 3, "tif_xyr") if tif_xyr is not None else None
    return tif_json, xyr


def _map_source(path: PathLike, map_options: Optional[Mapping[str, Any]], name: str) -> str:
    """A map file with the options of :func:`preston.read_map`, as a ``[map]`` table (JSON)."""
    from . import MAP_OPTIONS, _abs, _dumps, _map_options

    opts = dict(map_options or {})
    unknown = sorted(set(opts) - set(MAP_OPTIONS))
    if unknown:
        raise InputError(f"{name}: unknown map options {unknown} (known: {', '.join(MAP_OPTIONS)})")
    return _dumps({"file": _abs(path), **_map_options(opts)})


def calibrate(
    *,
    before: PathLike,
    after: PathLike,
    program: PathLike,
    tif: Optional[PathLike] = None,
    tif_xyr: Optional[ArrayLike] = None,
    gaussian: Optional[Mapping[str, float]] = None,
    a_max_mm_per_s2: Optional[float] = None,
    corner_angle_deg: float = 60.0,
    dialect: Optional[str] = None,
    model: str = "full",
    fit_power: bool = False,
    lattice_pitch_mm: Optional[float] = None,
    map_shift_sigma_mm: Optional[float] = None,
    map_options: Optional[Mapping[str, Any]] = None,
    out: Optional[PathLike] = None,
    plots: bool = False,
    plot_format: str = "png",
    require_converged: bool = False,
) -> dict:
    """The tool that actually ran (``preston calibrate``), learned from the map measured
    ``before`` a run, the map measured ``after`` it (any grid; the before map, on a regular grid
    with dropouts allowed, is resampled at its points), the ``program`` that ran (a G-code file,
    executed as the controller ran it: with ``a_max_mm_per_s2`` acceleration-limited look-ahead
    stopping at turns above ``corner_angle_deg``, else every block at its feed; ``dialect``
    default from its header) and the spot test (``tif`` CSV file, ``tif_xyr`` ``(N, 3)`` grid
    samples, or ``gaussian`` ``dict(sigma_mm=, peak_rate_nm_per_s=, truncation_radius_mm=)``).
    Both maps are read with ``map_options`` (those of :func:`preston.read_map`).

    ``model``: ``"full"`` (rate, width, centroid offset, shape, drift, and a free-form correction
    where the data support it), ``"shape"`` (no free-form correction) or ``"basic"`` (rate,
    width, offset and drift). ``fit_power`` fits a power term besides the piston and tilt each
    measurement drops; ``lattice_pitch_mm`` the convolution lattice's pitch (default: the TIF's
    second-moment radius / 10). ``map_shift_sigma_mm``: the standard deviation of a shift between
    the two measurements (default half a pixel of the map before; ``0``: the maps are in one
    frame and no shift is tried); a shift is kept only where it lowers the fit's RMS by 5% or
    more (``result["map_shift"]`` says whether it was, with the fit's RMS with and without).

    Returns the calibration record as a dict: the keys of ``calibration.json``
    (``rate_factor``, ``width_factor``, ``offset_x_mm``, ``offset_y_mm``, ``drift_per_hour``,
    ``ellipticity``, ``skew_x``, ... each with ``<key>_sigma``; ``held``, ``fit_rms_nm``,
    ``noise_rms_nm``, ``tif_file``, ``tif_sha256``, ...) plus ``tif_xyr``, the calibrated TIF's
    grid samples ``(N, 3)`` (x_mm, y_mm, rate_nm_per_s: what ``tif.csv`` holds). With ``out``
    writes ``calibration.json``, ``tif.csv`` and ``removal.csv`` there (with ``plots`` the
    figures too, as ``plot_format``), all or none: ``preston.solve(..., calibration=out +
    "/calibration.json")`` plans the next run with them. A fit that stops before converging is
    ``status`` in the dict, or :class:`NotConvergedError` with ``require_converged=True``."""
    from . import _abs, _dumps

    if model not in MODELS:
        raise InputError(f"calibrate: model must be one of {', '.join(MODELS)}, got {model!r}")
    tif_json, xyr = _tif_arguments(tif, tif_xyr, gaussian)
    settings = {
        "fit_shape": model != "basic",
        "freeform": model == "full",
        "fit_power": bool(fit_power),
        "fit_map_shift": map_shift_sigma_mm != 0,
        "lattice_pitch_mm": lattice_pitch_mm,
    }
    if map_shift_sigma_mm:
        settings["prior"] = {"map_shift_sigma_mm": float(map_shift_sigma_mm)}
    record, (tx, ty, tr), converged = _preston.calibrate(
        _map_source(before, map_options, "before"),
        _map_source(after, map_options, "after"),
        _abs(program),
        tif_json,
        xyr,
        _abs(tif) if tif is not None else None,
        a_max_mm_per_s2,
        float(corner_angle_deg),
        dialect,
        _dumps(settings),
        _abs(out) if out is not None else None,
        plot_format if plots else None,
    )
    result = json.loads(record)
    result["tif_xyr"] = np.column_stack([tx, ty, tr])
    if require_converged and not converged:
        raise NotConvergedError(
            f"calibrate: the fit stopped before converging (status {result.get('status')}, "
            f"{result.get('iterations')} iterations)"
        )
    return result


def shop(
    surface: PathLike,
    *,
    program: Optional[PathLike] = None,
    tif: Optional[PathLike] = None,
    tif_xyr: Optional[ArrayLike] = None,
    gaussian: Optional[Mapping[str, float]] = None,
    a_max_mm_per_s2: Optional[float] = None,
    corner_angle_deg: float = 60.0,
    dialect: Optional[str] = None,
    tool_rate_factor: float = 1.0,
    tool_width_factor: float = 1.0,
    tool_offset_mm: Sequence[float] = (0.0, 0.0),
    tool_ellipticity: float = 0.0,
    tool_skew: float = 0.0,
    tool_skew_angle_deg: float = 0.0,
    tool_drift_per_run: float = 0.0,
    noise_rms_nm: float = 0.3,
    seed: int = 1,
    out: Optional[PathLike] = None,
) -> dict:
    """A visit to the virtual shop (``preston shop``), to rehearse the measure-calibrate-plan-polish
    loop. The shop keeps the part's true ``surface`` (CSV ``x_mm,y_mm,z_nm``: the
    ``surface_after.csv`` of the previous visit); it runs the ``program`` (a G-code file; without
    one the shop only measures) with the tool it really has, the spot test (``tif``, ``tif_xyr``
    or ``gaussian``) changed by ``tool_rate_factor``, ``tool_width_factor`` (volume kept),
    ``tool_offset_mm`` (x, y: where the tool lands off the programmed point), ``tool_ellipticity``
    (log stretch along x), ``tool_skew`` (relative rate change per second-moment radius along
    ``tool_skew_angle_deg``) and ``tool_drift_per_run`` (the rate's relative change from the run's
    first contact to its last), executed as the controller runs it (``a_max_mm_per_s2``,
    ``corner_angle_deg``, ``dialect``); and reads the part with an interferometer that adds
    ``noise_rms_nm`` of white noise (seeded by ``seed``) and drops piston and tilt.

    Returns a dict: the keys of ``shop.json`` (``tool``, ``tool_figures``: the true footprint's
    rate, width and centroid offset against the spot test, what a calibration should find;
    ``noise_rms_nm``, ``program_time_s``, ``true_rms_before_nm``, ``true_rms_after_nm``,
    ``measured_rms_nm``) plus the arrays ``x_mm``, ``y_mm``, ``surface_after_nm`` (the true
    surface) and ``measured_nm`` (what the interferometer reads). With ``out`` writes
    ``surface_after.csv``, ``measured.csv`` and ``shop.json`` there, all or none."""
    from . import _abs, _dumps

    tif_json, xyr = _tif_arguments(tif, tif_xyr, gaussian)
    offset = [float(v) for v in tool_offset_mm]
    if len(offset) != 2:
        raise InputError(f"shop: tool_offset_mm takes two values (x, y), got {len(offset)}")
    tool = {
        "rate_factor": float(tool_rate_factor),
        "width_factor": float(tool_width_factor),
        "offset_x_mm": offset[0],
        "offset_y_mm": offset[1],
        "ellipticity": float(tool_ellipticity),
        "skew": float(tool_skew),
        "skew_angle_deg": float(tool_skew_angle_deg),
        "drift_per_run": float(tool_drift_per_run),
    }
    record, (x, y, after, measured) = _preston.shop(
        _map_source(surface, None, "surface"),
        _abs(program) if program is not None else None,
        tif_json,
        xyr,
        a_max_mm_per_s2,
        float(corner_angle_deg),
        dialect,
        _dumps(tool),
        float(noise_rms_nm),
        int(seed),
        _abs(out) if out is not None else None,
    )
    result = json.loads(record)
    result.update({"x_mm": x, "y_mm": y, "surface_after_nm": after, "measured_nm": measured})
    return result
