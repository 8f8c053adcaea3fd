"""The package in Python's terms: exceptions that are the builtins they stand for, messages that
name the keyword, lattice results as 2-D grids, R as a scipy matrix, the CLI's defaults, and the
programs as text or files both ways."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import preston

DATA = Path(__file__).resolve().parents[2] / "data"

#: Relative tolerance of R t against the solver's removal (the same sums in another order).
REMOVAL_REL_TOL = 1e-9


def small_case(nx: int = 40, ny: int = 20, pitch: float = 0.5):
    xs, ys = np.meshgrid(np.arange(nx) * pitch, np.arange(ny) * pitch)
    x, y = xs.ravel(), ys.ravel()
    z = 20.0 + 8.0 * np.sin(x / 3.0) + 5.0 * np.cos(y / 2.0)
    return x, y, z


GAUSS = {"sigma_mm": 1.0, "peak_rate_nm_per_s": 5.0, "truncation_radius_mm": 3.0}


def test_input_errors_are_value_errors_naming_the_keyword():
    bad = np.zeros((5, 2))
    with pytest.raises(ValueError) as e:
        preston.solve(map_xyz=bad, gaussian=GAUSS, raster_pitch_mm=1.0, v_max=3000.0)
    assert "map_xyz" in str(e.value)
    assert isinstance(e.value, preston.PrestonError)
    assert isinstance(e.value, preston.InputError)


def test_an_unknown_key_is_named_by_its_keyword_not_a_json_position():
    x, y, z = small_case()
    with pytest.raises(ValueError) as e:
        preston.solve(
            map_xyz=(x, y, z),
            gaussian={"sigma_mm": 1.0, "peak": 5.0},
            raster_pitch_mm=1.0,
            v_max=3000.0,
        )
    msg = str(e.value)
    assert "gaussian" in msg and "peak" in msg, msg
    assert "column" not in msg and "line 1" not in msg, msg
    with pytest.raises(ValueError) as e:
        preston.solve(
            map_xyz=(x, y, z), gaussian=GAUSS, raster_pitch_mm=1.0, v_max=3000.0,
            raster_along="diagonal",
        )
    msg = str(e.value)
    assert "raster_along" in msg and "diagonal" in msg and "column" not in msg, msg


def test_file_errors_are_os_errors():
    with pytest.raises(FileNotFoundError) as e:
        preston.read_map(DATA / "no_such_map.csv")
    assert isinstance(e.value, OSError)
    assert isinstance(e.value, preston.InputFileError)
    assert isinstance(e.value, preston.InputError)
    assert "no_such_map.csv" in str(e.value)


def test_a_gaussian_without_truncation_gets_the_cli_default_of_three_sigma():
    x, y, z = small_case()
    common = dict(map_xyz=(x, y, z), raster_pitch_mm=1.0, v_max=3000.0)
    a = preston.solve(gaussian={"sigma_mm": 1.0, "peak_rate_nm_per_s": 5.0}, **common)
    b = preston.solve(gaussian=GAUSS, **common)
    np.testing.assert_array_equal(a.dwell_s, b.dwell_s)


def test_lattice_results_come_as_grids_with_their_axes():
    x, y, z = small_case()
    keep = ~((x > 5.0) & (x < 7.0) & (y > 3.0) & (y < 5.0))  # a hole
    r = preston.solve(
        map_xyz=(x[keep], y[keep], z[keep]), gaussian=GAUSS, raster_pitch_mm=1.0, v_max=3000.0
    )
    g = r.residual_grid
    assert g.values.shape == (20, 40)
    np.testing.assert_allclose(g.x_mm, np.arange(40) * 0.5)
    np.testing.assert_allclose(g.y_mm, np.arange(20) * 0.5)
    i = np.rint(r.map_x_mm / 0.5).astype(int)
    j = np.rint(r.map_y_mm / 0.5).astype(int)
    np.testing.assert_array_equal(g.values[j, i], r.residual_nm)
    assert np.isnan(g.values).sum() == (~keep).sum()
    np.testing.assert_array_equal(r.error_grid.values[j, i], r.z_nm)
    with pytest.raises(ValueError):
        r.grid("feed")


def test_influence_matrix_is_the_solves_r():
    sp = pytest.importorskip("scipy.sparse")
    x, y, z = small_case()
    kw = dict(map_xyz=(x, y, z), gaussian=GAUSS, raster_pitch_mm=1.0, v_max=3000.0)
    r = preston.solve(operator="sparse", **kw)
    R = preston.influence_matrix(**kw)
    assert sp.issparse(R)
    assert R.shape == (x.size, r.dwell_s.size)
    removal = R @ r.dwell_s
    scale = np.abs(r.removal_nm).max()
    assert np.abs(removal - r.removal_nm).max() <= REMOVAL_REL_TOL * scale
    # The Gaussian's peak rate at a dwell point on a map point.
    assert R.max() <= 5.0 + 1e-12
    with pytest.raises(ValueError):
        preston.influence_matrix(bogus=1, **kw)


def test_programs_go_as_text_or_file_both_ways(tmp_path):
    x, y, z = small_case()
    map_file = tmp_path / "m.csv"
    np.savetxt(map_file, np.column_stack([x, y, z]), delimiter=",", header="x_mm,y_mm,z_nm",
               comments="")
    r = preston.solve(map=map_file, gaussian=GAUSS, raster_pitch_mm=1.0, v_max=3000.0)
    out = tmp_path / "p.nc"
    text = preston.nc(
        np.column_stack([r.dwell_x_mm, r.dwell_y_mm]), r.dwell_s, v_max_mm_per_min=3000.0, out=out
    )
    assert out.read_text() == text
    a = preston.simulate_program(map_file, text, gaussian=GAUSS)
    b = preston.simulate_program(map_file, out, gaussian=GAUSS)
    np.testing.assert_array_equal(a["removal_nm"], b["removal_nm"])
    assert a["check"]["max_relative_error"] < 0.05


def test_write_gives_the_report_page_and_colour_limits(tmp_path):
    x, y, z = small_case()
    r = preston.solve(map_xyz=(x, y, z), gaussian=GAUSS, raster_pitch_mm=1.0, v_max=3000.0)
    r.write(tmp_path, plots=True, report=True, color_limits=(-5, 5))
    html = (tmp_path / "report.html").read_text()
    assert f'data-key="rms_after_nm" data-value="{r.report["rms_after_nm"]!r}"' in html
    assert (tmp_path / "psd_2d.csv").is_file()
    with pytest.raises(ValueError):
        r.write(tmp_path / "bad", color_limits=(5, -5))
