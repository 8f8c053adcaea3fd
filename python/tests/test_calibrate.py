"""The shop loop from Python: a plan, its program, a run in the virtual shop with a tool that is
not the spot test, :func:`preston.calibrate` learning that tool from the measured change (the
same record as ``preston calibrate`` on the same files), and :func:`preston.solve` with
``calibration=`` stating what the interferometer is expected to read. Bad inputs raise
:class:`preston.InputError` naming the file, and nothing is written."""

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

import preston

SIGMA_MM = 1.4
PEAK_NM_PER_S = 12.0
TRUNCATION_MM = 6.0
GAUSSIAN = dict(sigma_mm=SIGMA_MM, peak_rate_nm_per_s=PEAK_NM_PER_S, truncation_radius_mm=TRUNCATION_MM)
GAUSSIAN_FLAGS = [
    "--gaussian-sigma-mm", str(SIGMA_MM),
    "--gaussian-peak-nm-per-s", str(PEAK_NM_PER_S),
    "--gaussian-truncation-mm", str(TRUNCATION_MM),
]

#: The shop's true tool.
TRUE_RATE, TRUE_WIDTH, TRUE_OFFSET_MM = 1.06, 1.03, (0.1, -0.08)
NOISE_RMS_NM = 0.3

#: The figures are recovered within these (relative, relative, mm).
RATE_TOL, WIDTH_TOL, OFFSET_TOL_MM = 0.005, 0.01, 0.02
#: The shop's footprint figures are the tool's as set within this (moments on a grid).
FIGURES_TOL = 1e-3
#: The Python record equals the CLI's on the same files: the same engine, printed as shortest
#: round-trip decimals.
SAME_REL = 1e-12

PLAN = dict(raster_pitch_mm=0.5, v_max=3000.0, v_min=1.0, a_max=1000.0, rho=0.01,
            accel_method="correction-passes")


def form_nm(x, y):
    """Smooth terms a run corrects and ripples of periods 4.0 to 4.2 mm it partly cannot."""
    u, v = x - 15.0, y - 8.0
    return (
        60.0 * np.sin(0.21 * u) * np.cos(0.33 * v + 0.4)
        + 40.0 * np.cos(0.13 * u + 0.17 * v)
        + 0.08 * u * u
        + 3.0 * np.sin(1.5 * u + 0.6 * v)
        + 2.0 * np.cos(1.0 * u - 1.2 * v + 0.7)
        + 1.5 * np.sin(1.5 * v + 0.3 * u)
    )


def write_map(path: Path, dx_mm: float = 0.0) -> Path:
    """The 30 x 16 mm map at 0.5 mm, shifted by ``dx_mm`` along x."""
    x, y = (a.ravel() for a in np.meshgrid(np.arange(61) * 0.5, np.arange(33) * 0.5))
    np.savetxt(path, np.column_stack([x + dx_mm, y, form_nm(x, y)]), delimiter=",",
               header="x_mm,y_mm,z_nm", comments="", fmt="%.9g")
    return path


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One run of the loop: the measured maps, the program, the shop's record, the calibration."""
    d = tmp_path_factory.mktemp("shop")
    surface = write_map(d / "surface.csv")
    v0 = preston.shop(surface, gaussian=GAUSSIAN, noise_rms_nm=NOISE_RMS_NM, seed=3, out=d / "v0")
    before = d / "v0" / "measured.csv"
    assert v0["program_time_s"] == 0.0
    assert np.array_equal(v0["surface_after_nm"], np.loadtxt(surface, delimiter=",", skiprows=1)[:, 2])
    plan = preston.solve(map=before, gaussian=GAUSSIAN, **PLAN)
    program = d / "prog.nc"
    preston.nc(np.column_stack([plan.dwell_x_mm, plan.dwell_y_mm]), plan.dwell_s,
               v_max_mm_per_min=3000.0, a_max_mm_per_s2=1000.0, out=program)
    visit = preston.shop(
        d / "v0" / "surface_after.csv", program=program, gaussian=GAUSSIAN, a_max_mm_per_s2=1000.0,
        tool_rate_factor=TRUE_RATE, tool_width_factor=TRUE_WIDTH, tool_offset_mm=TRUE_OFFSET_MM,
        noise_rms_nm=NOISE_RMS_NM, seed=4, out=d / "shop",
    )
    after = d / "shop" / "measured.csv"
    record = preston.calibrate(before=before, after=after, program=program, gaussian=GAUSSIAN,
                               a_max_mm_per_s2=1000.0, out=d / "calibration")
    return dict(dir=d, before=before, after=after, program=program, visit=visit, record=record)


def test_shop_writes_what_it_returns(run):
    d, visit = run["dir"], run["visit"]
    written = json.loads((d / "shop" / "shop.json").read_text())
    for k in ("tool", "tool_figures", "noise_rms_nm", "program_time_s", "true_rms_after_nm"):
        assert visit[k] == written[k], k
    measured = np.loadtxt(d / "shop" / "measured.csv", delimiter=",", skiprows=1)
    assert np.allclose(measured[:, 2], visit["measured_nm"], rtol=0.0, atol=1e-6)
    for key, set_to in [("rate_factor", TRUE_RATE), ("width_factor", TRUE_WIDTH),
                        ("offset_x_mm", TRUE_OFFSET_MM[0]), ("offset_y_mm", TRUE_OFFSET_MM[1])]:
        assert abs(visit["tool_figures"][key] - set_to) < FIGURES_TOL, key
    # The run removed material: the true surface after is lower than before wherever it ran.
    assert visit["program_time_s"] > 0.0
    assert visit["true_rms_after_nm"] < visit["true_rms_before_nm"]


def test_calibrate_recovers_the_true_tool(run):
    r, truth = run["record"], run["visit"]["tool_figures"]
    for key in ("rate_factor", "width_factor", "offset_x_mm", "offset_y_mm", "drift_per_hour"):
        assert np.isfinite(r[key]), key
        assert np.isfinite(r[f"{key}_sigma"]) and r[f"{key}_sigma"] >= 0.0, key
    for key in ("fit_rms_nm", "noise_rms_nm"):
        assert r[key] >= 0.0, key
    assert r["tif_file"] == "tif.csv"
    assert abs(r["rate_factor"] / truth["rate_factor"] - 1.0) < RATE_TOL, r
    assert abs(r["width_factor"] / truth["width_factor"] - 1.0) < WIDTH_TOL, r
    assert abs(r["offset_x_mm"] - truth["offset_x_mm"]) < OFFSET_TOL_MM, r
    assert abs(r["offset_y_mm"] - truth["offset_y_mm"]) < OFFSET_TOL_MM, r
    # The returned TIF is tif.csv, and the written record is the returned one.
    d = run["dir"] / "calibration"
    tif = np.loadtxt(d / "tif.csv", delimiter=",", skiprows=1)
    assert np.allclose(tif, r["tif_xyr"], rtol=0.0, atol=1e-6)
    written = json.loads((d / "calibration.json").read_text())
    assert written["rate_factor"] == r["rate_factor"]
    assert written["tif_sha256"] == r["tif_sha256"] != ""


def test_calibrate_equals_the_cli(run, preston_bin, tmp_path):
    out = tmp_path / "cli"
    p = subprocess.run(
        [str(preston_bin), "calibrate", "--quiet", "--before", str(run["before"]), "--after",
         str(run["after"]), "--program", str(run["program"]), *GAUSSIAN_FLAGS,
         "--a-max-mm-per-s2", "1000", "--out", str(out)],
        capture_output=True, text=True,
    )
    assert p.returncode == 0, p.stderr
    cli = json.loads((out / "calibration.json").read_text())
    py = run["record"]
    for k in ("rate_factor", "width_factor", "offset_x_mm", "offset_y_mm", "drift_per_hour",
              "rate_factor_sigma", "fit_rms_nm", "noise_rms_nm"):
        assert py[k] == pytest.approx(cli[k], rel=SAME_REL, abs=0.0), k
    assert py["points"] == cli["points"]
    assert py["tif_sha256"] == cli["tif_sha256"]


def test_calibrate_without_out_writes_nothing(run, tmp_path):
    r = preston.calibrate(before=run["before"], after=run["after"], program=run["program"],
                          gaussian=GAUSSIAN, a_max_mm_per_s2=1000.0, model="basic")
    assert r["freeform"] is None
    assert r["tif_sha256"] != ""
    assert abs(r["rate_factor"] / run["visit"]["tool_figures"]["rate_factor"] - 1.0) < RATE_TOL


def test_calibrate_map_shift_sigma_is_the_cli_flag(run, preston_bin, tmp_path):
    """``map_shift_sigma_mm=0`` tries no shift (``map_shift`` null), as ``--map-shift-sigma-mm 0``
    does; by default a shift is tried and, the shop having made none, not kept."""
    assert run["record"]["map_shift"]["kept"] is False
    r = preston.calibrate(before=run["before"], after=run["after"], program=run["program"],
                          gaussian=GAUSSIAN, a_max_mm_per_s2=1000.0, model="basic",
                          map_shift_sigma_mm=0)
    assert r["map_shift"] is None
    out = tmp_path / "cli"
    p = subprocess.run(
        [str(preston_bin), "calibrate", "--quiet", "--before", str(run["before"]), "--after",
         str(run["after"]), "--program", str(run["program"]), *GAUSSIAN_FLAGS,
         "--a-max-mm-per-s2", "1000", "--model", "basic", "--map-shift-sigma-mm", "0",
         "--out", str(out)],
        capture_output=True, text=True,
    )
    assert p.returncode == 0, p.stderr
    cli = json.loads((out / "calibration.json").read_text())
    assert cli["map_shift"] is None
    assert r["rate_factor"] == pytest.approx(cli["rate_factor"], rel=SAME_REL, abs=0.0)
    with pytest.raises(preston.InputError, match="map_shift_sigma_mm"):
        preston.calibrate(before=run["before"], after=run["after"], program=run["program"],
                          gaussian=GAUSSIAN, a_max_mm_per_s2=1000.0, map_shift_sigma_mm=-1.0)


def test_solve_with_the_calibration_states_the_expected_reading(run):
    c = run["dir"] / "calibration"
    r = preston.solve(map=run["after"], tif=c / "tif.csv", calibration=c / "calibration.json", **PLAN)
    rep = r.report
    lo, hi = rep["expected_rms_range_nm"]
    assert lo <= rep["expected_rms_nm"] <= hi
    assert rep["run_pays"] == (rep["expected_rms_nm"] < rep["rms_before_nm"])
    # The calibration's uncertainty is what the reading was drawn from.
    u = rep["expected"]["uncertainty"]
    assert u["width_sigma"] == pytest.approx(
        run["record"]["width_factor_sigma"] / run["record"]["width_factor"], rel=1e-12)
    # The calibrated TIF beside calibration.json is the TIF when none is given.
    r2 = preston.solve(map=run["after"], calibration=c / "calibration.json", **PLAN)
    assert r2.report["expected_rms_nm"] == rep["expected_rms_nm"]


def test_calibrate_bad_inputs(run, tmp_path):
    far = write_map(tmp_path / "far.csv", dx_mm=100.0)
    out = tmp_path / "bad"
    with pytest.raises(preston.InputError, match="far.csv"):
        preston.calibrate(before=run["before"], after=far, program=run["program"],
                          gaussian=GAUSSIAN, a_max_mm_per_s2=1000.0, out=out)
    assert not out.exists()
    with pytest.raises(preston.InputError, match="model"):
        preston.calibrate(before=run["before"], after=run["after"], program=run["program"],
                          gaussian=GAUSSIAN, model="everything")
    with pytest.raises(preston.InputError, match="one of tif="):
        preston.calibrate(before=run["before"], after=run["after"], program=run["program"])
    bad = dict(json.loads((run["dir"] / "calibration" / "calibration.json").read_text()))
    bad["width_factor_sigma"] = -0.01
    bad_file = run["dir"] / "calibration" / "negative_sigma.json"
    bad_file.write_text(json.dumps(bad))
    with pytest.raises(preston.InputError, match="negative_sigma.json.*width_factor_sigma"):
        preston.solve(map=run["after"], calibration=bad_file, **PLAN)
    with pytest.raises(preston.InputError, match="tool_offset_mm"):
        preston.shop(run["before"], gaussian=GAUSSIAN, tool_offset_mm=(0.1,))
