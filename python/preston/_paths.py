"""Tool paths with every option of ``preston path``: rasters and intersection rasters (point step,
margin, arc turns, clear-aperture clipping), the chord-height line on a design surface, and the
projection of any path onto a surface. Lengths mm, chord heights um; numpy float64 arrays."""

from __future__ import annotations

import json
import os
from typing import Any, Mapping, Optional, Tuple, Union

import numpy as np

from . import _preston
from ._preston import InputError

ArrayLike = Any
Surface = Union[str, "os.PathLike[str]", Mapping[str, Any]]

#: The columns of ``preston path``'s CSV, in order.
COLUMNS = ("x_mm", "y_mm", "z_mm", "tx", "ty", "tz", "ds_mm")


class ToolPath:
    """A tool path as ``preston path`` writes it (numpy ``float64`` arrays, path order):

    * ``x_mm``, ``y_mm``, ``z_mm`` -- the points, mm (``z_mm`` on the surface, 0 without one);
    * ``tx``, ``ty``, ``tz`` -- the unit tangent of the path at each point (along the surface);
    * ``ds_mm`` -- the path length each point stands for, mm (half the distance to each
      neighbour, measured along the surface);
    * ``summary`` -- the dict the CLI prints (``kind``, ``points``, ``lines``, ...).

    ``xy`` is the ``(N, 2)`` array ``solve(dwell_xy=...)`` takes; ``columns`` the ``(N, 7)``
    array of the CSV's columns (:data:`COLUMNS`)."""

    __slots__ = COLUMNS + ("summary",)

    def __init__(self, cols: Tuple[np.ndarray, ...], summary: dict) -> None:
        for name, c in zip(COLUMNS, cols):
            setattr(self, name, c)
        self.summary = summary

    @property
    def xy(self) -> np.ndarray:
        """The points as an ``(N, 2)`` array x_mm, y_mm (for ``solve(dwell_xy=...)``)."""
        return np.column_stack([self.x_mm, self.y_mm])

    @property
    def columns(self) -> np.ndarray:
        """The ``(N, 7)`` array of ``x_mm, y_mm, z_mm, tx, ty, tz, ds_mm`` (the CSV's rows)."""
        return np.column_stack([getattr(self, c) for c in COLUMNS])

    def __len__(self) -> int:
        return len(self.x_mm)

    def __repr__(self) -> str:
        return f"<preston.ToolPath {self.summary.get('kind', 'path')}: {len(self)} points>"


def _surface(surface: Optional[Surface]) -> Optional[str]:
    if surface is None:
        return None
    from ._workflow import _surface_json

    return _surface_json(surface)


def _pair(v: Any, name: str) -> Tuple[float, float]:
    try:
        a, b = v
        return float(a), float(b)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected two numbers (a, b), got {v!r}") from None


def _lines(
    x_range_mm: Tuple[float, float],
    y_range_mm: Tuple[float, float],
    pitch_mm: float,
    along: str,
    iteration: Optional[int],
    step_mm: Optional[float],
    margin_mm: float,
    arc_radius_mm: Optional[float],
    arc_tolerance_um: float,
    aperture_xy: Optional[ArrayLike],
    surface: Optional[Surface],
) -> ToolPath:
    from . import _columns

    if iteration is not None and int(iteration) < 0:
        raise InputError(f"iteration must be 0 or more, got {iteration}")
    cols, summary = _preston.path_lines(
        _pair(x_range_mm, "x_range_mm"),
        _pair(y_range_mm, "y_range_mm"),
        float(pitch_mm),
        along,
        None if iteration is None else int(iteration),
        None if step_mm is None else float(step_mm),
        float(margin_mm),
        None if arc_radius_mm is None else float(arc_radius_mm),
        float(arc_tolerance_um),
        _columns(aperture_xy, 2, "aperture_xy") if aperture_xy is not None else None,
        _surface(surface),
    )
    return ToolPath(cols, json.loads(summary))


def path_raster(
    x_range_mm: Tuple[float, float],
    y_range_mm: Tuple[float, float],
    pitch_mm: float,
    *,
    along: str = "x",
    step_mm: Optional[float] = None,
    margin_mm: float = 0.0,
    arc_radius_mm: Optional[float] = None,
    arc_tolerance_um: float = 1.0,
    aperture_xy: Optional[ArrayLike] = None,
    surface: Optional[Surface] = None,
) -> ToolPath:
    """A serpentine raster (``preston path raster``) over the box ``x_range_mm`` x
    ``y_range_mm`` extended by ``margin_mm`` on every side: lines along ``along`` (``"x"`` or
    ``"y"``) ``pitch_mm`` apart (every point of the box within P/2 of a line), points at most
    ``step_mm`` (default: the pitch) apart along them, odd lines backwards.

    ``arc_radius_mm`` (at most P/2) joins the lines by tangent-continuous quarter arcs whose
    chords stay within ``arc_tolerance_um`` of the arc; without it the turns are sharp.
    ``aperture_xy`` (``(N, 2)`` polygon, mm, first vertex not repeated) keeps the points inside
    the clear aperture or within ``margin_mm`` of it. ``surface`` (a surface JSON file or the dict
    :func:`preston.fit` returns) projects the path onto the design (z, 3-D tangents, ``ds_mm``
    along the surface). Returns a :class:`ToolPath`; its summary has ``points``, ``lines`` and
    ``length_mm``."""
    return _lines(
        x_range_mm, y_range_mm, pitch_mm, along, None, step_mm, margin_mm, arc_radius_mm,
        arc_tolerance_um, aperture_xy, surface,
    )


def path_intersection(
    x_range_mm: Tuple[float, float],
    y_range_mm: Tuple[float, float],
    pitch_mm: float,
    iteration: int,
    *,
    step_mm: Optional[float] = None,
    margin_mm: float = 0.0,
    arc_radius_mm: Optional[float] = None,
    arc_tolerance_um: float = 1.0,
    aperture_xy: Optional[ArrayLike] = None,
    surface: Optional[Surface] = None,
) -> ToolPath:
    """The crossed (intersection) raster of run ``iteration`` (0-based) of a sequence
    (``preston path intersection``): lines along x, then y, then x shifted by P/2, then y shifted
    by P/2, repeating, so that successive runs' ripples cancel. The other options are those of
    :func:`path_raster`. The summary has ``iteration``, ``along``, ``shift_mm``, ``points`` and
    ``lines``."""
    return _lines(
        x_range_mm, y_range_mm, pitch_mm, "x", iteration, step_mm, margin_mm, arc_radius_mm,
        arc_tolerance_um, aperture_xy, surface,
    )


def path_chord_height(
    surface: Surface,
    line_x_mm: float,
    y_range_mm: Tuple[float, float],
    tool_radius_mm: float,
    eps_um: Tuple[float, float],
    *,
    grow_mm: float = 0.10,
    shrink_mm: float = 0.02,
) -> ToolPath:
    """Equal chord-height points (``preston path chord-height``) along the line
    ``x = line_x_mm`` from ``y_range_mm[0]`` to ``y_range_mm[1]`` on the design ``surface`` (file
    or dict), for a tool of ``tool_radius_mm``: every step is as long as keeps the chord's height
    above the surface within the window ``eps_um = (E1, E2)`` (um), the search growing by
    ``grow_mm`` and shrinking by ``shrink_mm``. The path is projected onto the surface.

    Returns a :class:`ToolPath` whose summary has the CLI's keys (``min_step_mm``,
    ``max_step_mm``, ``min_chord_height_um``, ``max_chord_height_um``, ``last_chord_height_um``,
    ``last_step_mm``) and, as arrays, ``steps_mm`` (each step's 3-D chord length, mm) and
    ``chord_heights_um`` (each step's chord height: the largest distance between the surface
    curve and the chord, um)."""
    cols, summary, steps, heights = _preston.path_chord_height(
        _surface(surface),
        float(line_x_mm),
        _pair(y_range_mm, "y_range_mm"),
        float(tool_radius_mm),
        _pair(eps_um, "eps_um"),
        float(grow_mm),
        float(shrink_mm),
    )
    s = json.loads(summary)
    s["steps_mm"] = steps
    s["chord_heights_um"] = heights * 1e3
    return ToolPath(cols, s)


def path_project(points_xy: ArrayLike, surface: Optional[Surface] = None) -> ToolPath:
    """Any path (``(N, 2)`` points or ``(x_mm, y_mm)`` such as :func:`preston.path_spiral`
    returns, in path order, mm) projected onto the design ``surface`` (file or dict; flat at z = 0
    without one), as ``preston path ... --surface`` writes it: z, unit tangents and ``ds_mm``
    along the surface. Returns a :class:`ToolPath` (summary ``{"kind": "projected", "points":
    N}``)."""
    from . import _columns

    cols = _preston.path_project(_columns(points_xy, 2, "points_xy"), _surface(surface))
    return ToolPath(cols, {"kind": "projected", "points": len(cols[0])})
