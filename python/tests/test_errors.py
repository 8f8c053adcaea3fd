"""Every failure is a PrestonError subclass carrying Preston's message."""

import numpy as np
import pytest

import preston
from preston import _preston

from conftest import DATA


def test_hierarchy():
    for e in (preston.InputError, preston.SolverError, preston.NotConvergedError):
        assert issubclass(e, preston.PrestonError) and issubclass(e, Exception)
    assert preston.PrestonError.__module__ == "preston"


def test_missing_map_file_names_it(small_job, tmp_path):
    missing = tmp_path / "nowhere.csv"
    with pytest.raises(preston.InputError, match="nowhere.csv"):
        preston.solve(small_job, map=missing)


def test_missing_job_file():
    with pytest.raises(preston.InputError, match="no_such_job.toml"):
        preston.solve("no_such_job.toml")


def test_unknown_job_key_is_named(small_job):
    job = dict(small_job, machine={"v_max_mm_per_min": 3000.0, "vmin": 1.0})
    with pytest.raises(preston.InputError, match="vmin"):
        preston.solve(job)


def test_bad_choice_is_named(small_job):
    with pytest.raises(preston.InputError, match="fastest"):
        preston.solve(small_job, solver="fastest")
    with pytest.raises(preston.InputError, match="diagonal"):
        preston.solve(small_job, raster_along="diagonal")


def test_feed_limits(small_job):
    job = dict(small_job, machine={})
    with pytest.raises(preston.InputError, match="v_max_mm_per_min"):
        preston.solve(job)
    with pytest.raises(preston.InputError, match="v_max"):
        preston.solve(small_job, v_max=-5.0)


def test_incompatible_options(small_job):
    with pytest.raises(preston.InputError, match="cannot be used"):
        preston.solve(small_job, operator="fft", solver="qp")
    with pytest.raises(preston.InputError, match="min_time"):
        preston.solve(small_job, a_max=100.0, min_time=True)


def test_bad_arrays(small_job):
    with pytest.raises(preston.InputError, match=r"\(N, 3\)"):
        preston.solve(small_job, map_xyz=np.zeros((4, 2)))
    x, y, z = preston.read_map(small_job["map"]["file"])
    z = z.copy()
    z[3] = np.nan
    with pytest.raises(preston.InputError, match="not finite"):
        preston.solve(small_job, map_xyz=(x, y, z))
    tif = np.array([[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    with pytest.raises(preston.InputError, match="tif_xyr"):
        preston.solve(small_job, tif_xyr=tif)
    with pytest.raises(preston.InputError, match=r"\(N, 2\)"):
        preston.solve(small_job, dwell_xy=np.zeros(5))
    with pytest.raises(preston.InputError, match="not both"):
        preston.solve(small_job, map=small_job["map"]["file"], map_xyz=(x, y, z))
    with pytest.raises(preston.InputError, match="aperture"):
        preston.solve(small_job, map_xyz=(x, y, z), map_options={"aperture": "circle:5"})


def test_read_map_errors(tmp_path):
    with pytest.raises(preston.InputError, match="nothing.csv"):
        preston.read_map(tmp_path / "nothing.csv")
    with pytest.raises(preston.InputError, match="colour"):
        preston.read_map(DATA / "mirror_error_118x8mm.csv", colour="red")
    with pytest.raises(preston.InputError, match="furlong"):
        preston.read_map(DATA / "mirror_error_118x8mm.csv", units="mm,mm,furlong")
    bad = tmp_path / "bad.csv"
    bad.write_text("x_mm,y_mm,z_nm\n0,0,1\n1,0,abc\n")
    with pytest.raises(preston.InputError, match="line 3"):
        preston.read_map(bad)


def test_not_converged(small_job):
    r = preston.solve(small_job, solver="first-order", max_iterations=2, tolerance=1e-12)
    assert not r.converged and r.report["status"] == r.status != "converged"
    with pytest.raises(preston.NotConvergedError, match=r.status):
        preston.solve(small_job, solver="first-order", max_iterations=2, tolerance=1e-12, require_converged=True)


def test_numerical_failure_maps_to_solver_error():
    """The engine's numerical-failure error becomes SolverError (a hook raises one: no input
    reliably breaks the factorisations)."""
    with pytest.raises(preston.SolverError, match="numerical failure in test"):
        _preston._raise_numerical()


def test_other_functions_raise_prestons_message(small_job):
    with pytest.raises(preston.InputError, match="3 points cannot determine 65 parameters"):
        preston.fit(np.zeros((3, 3)), order=10)
    line = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    with pytest.raises(preston.InputError, match="klingon"):
        preston.nc(line, np.ones(3), dialect="klingon")
    with pytest.raises(preston.InputError, match="v_max_mm_per_min"):
        preston.nc(line, np.ones(3), v_max_mm_per_min=-5.0)
    with pytest.raises(preston.InputError, match="dwell_s has 2 entries, expected 3"):
        preston.nc(line, np.ones(2))
    g = small_job["tif"]["gaussian"]
    with pytest.raises(preston.InputError, match="dwell_s has 3 entries, expected 2"):
        preston.simulate(np.zeros((3, 3)), line[:2], np.ones(3), gaussian=g)
    with pytest.raises(preston.InputError, match="one of"):
        preston.simulate(np.zeros((3, 3)), line[:2], np.ones(2))
    with pytest.raises(preston.InputError, match="pitch_mm"):
        preston.raster((0, 10), (0, 10), -1.0)
    with pytest.raises(preston.InputError, match="got int"):
        preston.load_job(42)
    with pytest.raises(preston.InputError, match="threads"):
        preston.solve(small_job, threads=0)


def test_simulate_callback_exception_is_raised(small_job):
    x = np.arange(50.0) * 0.1
    events = []

    def stop(e):
        events.append(e)
        raise RuntimeError("stop here")

    with pytest.raises(RuntimeError, match="stop here"):
        preston.simulate(np.column_stack([x, 0 * x, 1 + 0 * x]), np.array([[0.0, 0.0], [1.0, 0.0]]), np.ones(2),
                         gaussian=small_job["tif"]["gaussian"], samples_per_point=4, progress=stop)
    assert len(events) == 1  # no call after the first exception


def test_keywords_go_through_the_engines_override_layer(small_job):
    # The CLI's flag names, `_` for `-`, and the package's short names, into the job's keys.
    j, _, _ = preston._job_of(
        small_job, v_max=2000.0, lambda_=0.5, spread_tolerance=1e-3, robust=False, edge="none"
    )
    assert j["machine"]["v_max_mm_per_min"] == 2000.0
    assert j["objective"]["lambda"] == 0.5
    assert j["solver"]["spread_tolerance"] == 1e-3
    assert j["solver"]["robust"] is False
    assert j["edge"]["method"] == "none"
    # One tolerance and one iteration limit for whichever solver runs, as --tolerance does.
    j, _, _ = preston._job_of(small_job, tolerance=1e-7, max_iterations=40)
    assert j["solver"]["tolerance"] == j["solver"]["first_order_tolerance"] == 1e-7
    assert j["solver"]["max_iterations"] == j["solver"]["first_order_max_iterations"] == 40
    with pytest.raises(preston.InputError, match="unknown keyword `vmax`"):
        preston.solve(small_job, vmax=3000.0)
    with pytest.raises(preston.InputError, match="not both"):
        preston.solve(small_job, dwell="d.csv", raster_pitch_mm=1.0)


def test_a_dwell_section_with_a_file_and_a_raster_is_refused_as_by_the_cli(small_job, tmp_path):
    # The package reads what it is not given through the engine's one reader of a job's inputs.
    d = tmp_path / "d.csv"
    d.write_text("x_mm,y_mm\n0,0\n1,0\n")
    job = dict(small_job, dwell={"file": str(d), "raster_pitch_mm": 1.0})
    with pytest.raises(preston.InputError, match="raster_pitch_mm"):
        preston.solve(job)
