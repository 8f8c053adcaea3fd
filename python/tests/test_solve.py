"""preston.solve against the CLI on the sample job, the arrays path, the progress callback and
the release of the interpreter while the engine runs."""

import json
import subprocess
import threading
import time

import numpy as np
import pytest

import preston

from conftest import DATA

# Dwell times equal to the CLI's within this relative tolerance (the same engine, same inputs).
REL_TOL = 1e-12


def read_csv(path):
    with open(path) as f:
        header = f.readline().strip().split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


@pytest.fixture(scope="module")
def cli_out(preston_bin, sample_job, tmp_path_factory):
    out = tmp_path_factory.mktemp("cli")
    done = subprocess.run(
        [str(preston_bin), "solve", "--job", str(sample_job), "--out", str(out), "--json"],
        check=True,
        capture_output=True,
    )
    (out / "stdout.json").write_bytes(done.stdout)
    return out


@pytest.fixture(scope="module")
def py_job_result(sample_job):
    return preston.solve(sample_job)


def assert_close_rel(a, b, rel=REL_TOL):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape
    assert np.all(np.abs(a - b) <= rel * np.abs(b)), np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300))


def test_sample_job_equals_cli(cli_out, py_job_result):
    r = py_job_result
    header, d = read_csv(cli_out / "dwell.csv")
    assert header == ["x_mm", "y_mm", "ds_mm", "dwell_s", "feed_mm_per_min"]
    for arr in (r.dwell_s, r.feed_mm_per_min, r.residual_nm):
        assert isinstance(arr, np.ndarray) and arr.dtype == np.float64
    assert_close_rel(r.dwell_s, d[:, 3])
    assert_close_rel(r.feed_mm_per_min, d[:, 4])
    assert_close_rel(r.dwell_x_mm, d[:, 0])
    _, res = read_csv(cli_out / "residual.csv")
    np.testing.assert_allclose(r.residual_nm, res[:, 4], rtol=REL_TOL, atol=1e-9)
    np.testing.assert_allclose(r.removal_nm, res[:, 3], rtol=REL_TOL, atol=1e-9)
    cli_report = json.loads((cli_out / "report.json").read_text())
    assert set(r.report) == set(cli_report)
    for k in ("rms_before_nm", "rms_after_nm", "pv_after_nm", "total_dwell_s", "iterations", "status", "n", "m", "nnz"):
        assert r.report[k] == cli_report[k], k
    assert r.converged and r.status == cli_report["status"]


def test_program_check_is_the_clis(cli_out, py_job_result):
    # The program of the job's machine, checked once by the engine, read by both faces.
    cli = json.loads((cli_out / "stdout.json").read_text())["program_check"]
    check = py_job_result.program_check
    assert check == cli
    # The program as written delivers the plan: its stretches take the planned dwell.
    p = check["programmed"]
    assert abs(p["planned_total_s"] - py_job_result.report["total_dwell_s"]) <= 1e-6 * p["planned_total_s"]
    assert p["max_relative_error"] < 0.01


def test_arrays_in_equal_files_in(cli_out, py_job_result):
    """The map and TIF as arrays (no files), every option the job sets as a keyword (it sets no
    solver options: the defaults): the same dwell."""
    x, y, z = preston.read_map(DATA / "mirror_error_118x8mm.csv")
    tif = np.loadtxt(DATA / "tif_fluid_jet_10mm.csv", delimiter=",", skiprows=1)
    r = preston.solve(
        map_xyz=np.column_stack([x, y, z]),
        tif_xyr=tif,
        raster_pitch_mm=1.0,
        raster_along="x",
        v_max=3000.0,
        a_max=1000.0,
        accel_method="squared-speed",
        edge="gerchberg-papoulis",
        influence="point",
    )
    _, d = read_csv(cli_out / "dwell.csv")
    assert_close_rel(r.dwell_s, d[:, 3])
    # Arrays have no file format: the report leaves map_input out, and only that.
    assert set(py_job_result.report) - set(r.report) == {"map_input"}


def test_write_gives_the_cli_files(cli_out, py_job_result, tmp_path):
    py_job_result.write(tmp_path / "out")
    for f in ("dwell.csv", "residual.csv"):
        assert (tmp_path / "out" / f).read_text() == (cli_out / f).read_text(), f
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["rms_after_nm"] == py_job_result.report["rms_after_nm"]


def test_dwell_points_as_array_and_options(small_job):
    """Given dwell points reproduce the raster's solve; rho > 0 lowers the total dwell."""
    base = preston.solve(small_job)
    pts = np.column_stack([base.dwell_x_mm, base.dwell_y_mm])
    again = preston.solve(small_job, dwell_xy=pts)
    np.testing.assert_array_equal(again.dwell_s, base.dwell_s)
    cheaper = preston.solve(small_job, rho=50.0)
    assert cheaper.report["total_dwell_s"] < base.report["total_dwell_s"]
    g = small_job["tif"]["gaussian"]
    first = preston.solve(small_job, gaussian=g, solver="first-order", operator="sparse", tolerance=1e-7)
    assert first.report["solver"] != base.report["solver"]
    # Both near the optimum: residual RMS within 0.1% of the initial RMS of each other.
    gap = abs(first.report["rms_after_nm"] - base.report["rms_after_nm"])
    assert gap < 1e-3 * base.report["rms_before_nm"]
    # Feed = 60 ds / dwell, mm/min, never above v_max.
    np.testing.assert_allclose(base.feed_mm_per_min, 60.0 * base.ds_mm / base.dwell_s, rtol=1e-12)
    assert base.feed_mm_per_min.max() <= 3000.0 * (1 + 1e-9)
    slowest = preston.solve(small_job, v_min=600.0)
    assert slowest.feed_mm_per_min.min() >= 600.0 * (1 - 1e-9)
    assert base.feed_mm_per_min.min() < 600.0


def test_progress_callback(sample_job, py_job_result):
    events = []
    r = preston.solve(sample_job, progress=events.append)
    np.testing.assert_array_equal(r.dwell_s, py_job_result.dwell_s)
    stages = [(e["stage"], e["event"]) for e in events if e["event"] in ("start", "finish")]
    # The feed-limited solve, then the acceleration-limited iteration of the job's a_max.
    assert stages[:4] == [("assembly", "start"), ("assembly", "finish"), ("solve", "start"), ("solve", "finish")]
    assert stages[4:6] == [("loop", "start"), ("loop", "finish")]
    # The first assembly run (R); the executed-program check at the limit reports its own later.
    first_finish = next(i for i, e in enumerate(events) if e["stage"] == "assembly" and e["event"] == "finish")
    assembly = [e for e in events[: first_finish + 1] if e["stage"] == "assembly"]
    dones = [e["done"] for e in assembly]
    assert dones == sorted(dones) and assembly[-1]["done"] == assembly[-1]["total"] == r.report["n"]
    its = [e for e in events if e["event"] == "iteration"]
    # Iterations of the feed-limited solve, then the gradient steps (counted in the report's total).
    assert its and max(e["iteration"] for e in its) <= r.report["iterations"]
    assert all(np.isfinite(e["objective"]) for e in its)


def test_callback_exception_is_raised(small_job):
    class Stop(Exception):
        pass

    calls = []

    def cb(event):
        calls.append(event)
        raise Stop("stop here")

    with pytest.raises(Stop, match="stop here"):
        preston.solve(small_job, progress=cb)
    assert len(calls) == 1  # later calls are skipped once it has raised


def test_interpreter_released_during_solve(sample_job):
    """Another Python thread runs while the engine works: its ticks cover the whole solve with
    no gap near the solve's length (were the interpreter held, the ticker would stop for the
    whole solve: one gap as long as the solve). Gaps, not a tick rate, so a loaded host that
    slows the ticker does not fail it."""
    ticks = []
    done = threading.Event()

    def count():
        while not done.is_set():
            ticks.append(time.perf_counter())
            time.sleep(0.005)

    t = threading.Thread(target=count)
    t.start()
    while not ticks:
        time.sleep(0.001)
    start = time.perf_counter()
    try:
        preston.solve(sample_job)
        end = time.perf_counter()
    finally:
        done.set()
        t.join()
    elapsed = end - start
    assert elapsed > 0.2, f"the solve took {elapsed:.3f} s: too short to tell"
    during = [start] + [x for x in ticks if start < x < end] + [end]
    gaps = np.diff(during)
    assert len(during) >= 6, (len(during), elapsed)
    assert gaps.max() < 0.25 * elapsed, (gaps.max(), elapsed)


def test_threads_do_not_change_the_result(sample_job):
    """threads= installs a pool of that size for the call; every reduction has a fixed order, so
    the dwell is bit-identical on 1 thread, 3 threads and the default pool. The sample job's map
    spans several of the engine's 4,096-row summation chunks, so a reduction whose order
    followed the threads would show here."""
    one = preston.solve(sample_job, threads=1)
    assert one.report["m"] > 2 * 4096, one.report["m"]
    default = preston.solve(sample_job)
    three = preston.solve(sample_job, threads=3)
    np.testing.assert_array_equal(one.dwell_s, default.dwell_s)
    np.testing.assert_array_equal(three.dwell_s, default.dwell_s)
    np.testing.assert_array_equal(one.residual_nm, default.residual_nm)
    np.testing.assert_array_equal(three.residual_nm, default.residual_nm)


def test_accel_method_reaches_the_engine(small_job):
    """Each acceleration method reaches the engine: the report names it, the limit holds, and the
    refined method is never worse than squared speed; an unknown method is an input error."""
    results = {}
    for method in ("squared-speed", "scp-qp", "squared-speed-then-scp-qp"):
        r = preston.solve(small_job, a_max=50.0, accel_method=method)
        assert r.report["accel"]["method"] == method
        assert r.report["max_accel_mm_per_s2"] <= 50.0 * 1.01
        results[method] = r.report["objective"]
    assert results["squared-speed-then-scp-qp"] <= results["squared-speed"] * (1 + 1e-12)
    # Without a method named: correction passes against the program executed at the limit, as
    # on the command line and in a job.
    default = preston.solve(small_job, a_max=50.0)
    assert default.report["accel"]["method"] == "correction-passes"
    assert default.report["rms_after_nm"] == default.report["executed"]["rms_after_nm"]
    with pytest.raises(preston.InputError, match="newton"):
        preston.solve(small_job, a_max=50.0, accel_method="newton")


def test_each_first_order_method_reaches_the_qp_optimum(small_job):
    """The three first-order iterations (L-BFGS the default) by name, each at a tight tolerance
    within 1e-6 of the initial objective of the QP's (the map is nearly removable, so the
    optimum itself is tiny: 0.005 nm RMS from 25 nm), L-BFGS within 5e-9 (measured 2.4e-9 after
    its 20,000 iterations); the default is L-BFGS."""
    qp = preston.solve(small_job, solver="qp")
    f_qp = qp.report["objective"]
    f_0 = 0.5 * qp.report["m"] * qp.report["rms_before_nm"] ** 2
    runs = {
        m: preston.solve(small_job, solver="first-order", operator="sparse", first_order_method=m, tolerance=1e-10)
        for m in ("lbfgs", "fista", "newton-cg")
    }
    for m, r in runs.items():
        assert r.report["solver"] == "first-order", m
        rel = 5e-9 if m == "lbfgs" else 1e-6
        assert abs(r.report["objective"] - f_qp) <= rel * f_0, (m, r.report["objective"], f_qp, f_0)
    default = preston.solve(small_job, solver="first-order", operator="sparse", tolerance=1e-10)
    np.testing.assert_array_equal(default.dwell_s, runs["lbfgs"].dwell_s)


def test_lbfgs_memory_changes_the_path_not_the_optimum(small_job):
    """``lbfgs_memory`` reaches the engine (one pair takes another number of iterations than
    twenty) and both converge to within 6e-8 of the initial objective of the QP's optimum (the map
    is nearly removable; at the tolerance 1e-5 one pair lands 4.1e-8 away, twenty pairs 2.3e-8);
    out of range it is an input error naming it."""
    qp = preston.solve(small_job, solver="qp")
    f_qp = qp.report["objective"]
    f_0 = 0.5 * qp.report["m"] * qp.report["rms_before_nm"] ** 2
    runs = {
        pairs: preston.solve(small_job, solver="first-order", operator="sparse", lbfgs_memory=pairs, tolerance=1e-5)
        for pairs in (1, 20)
    }
    assert runs[1].report["iterations"] != runs[20].report["iterations"]
    for pairs, r in runs.items():
        assert r.report["status"] == "converged", (pairs, r.report["status"])
        assert abs(r.report["objective"] - f_qp) <= 6e-8 * f_0, (pairs, r.report["objective"], f_qp)
    with pytest.raises(preston.InputError, match="lbfgs_memory"):
        preston.solve(small_job, solver="first-order", lbfgs_memory=0)


def test_phase_stencil_operator_matches_the_assembled_matrix(small_job):
    """The 1 mm raster is off the 0.8 mm map lattice at 4 x 4 positions within a cell. The exact
    phase-stencil operator's plan, evaluated through the assembled contract (``simulate``), leaves
    the residual it reports; both operators' plans are equally good."""
    args = dict(solver="first-order", tolerance=1e-7)
    sparse = preston.solve(small_job, operator="sparse", **args)
    stencil = preston.solve(small_job, operator="stencil", **args)
    assert sparse.report["operator"] == "sparse"
    assert stencil.report["operator"] == "stencil"
    assert stencil.report["nnz"] == sparse.report["nnz"]
    m = np.loadtxt(small_job["map"]["file"], delimiter=",", skiprows=1)
    pts = np.column_stack([stencil.dwell_x_mm, stencil.dwell_y_mm])
    _, residual = preston.simulate(m, pts, stencil.dwell_s, gaussian=small_job["tif"]["gaussian"])
    rms = np.sqrt(np.mean(residual**2))
    assert abs(rms - stencil.report["rms_after_nm"]) <= 1e-9 * stencil.report["rms_before_nm"]
    gap = abs(stencil.report["rms_after_nm"] - sparse.report["rms_after_nm"])
    assert gap < 1e-3 * sparse.report["rms_before_nm"]
    with pytest.raises(preston.PrestonError, match="stencil"):
        preston.solve(small_job, operator="stencil", solver="qp")


def test_robust_keyword_is_the_cli_flag(small_job):
    """robust=True is --robust: the report compares the robust plan with the nominal plan per
    scenario, and its nominal RMS is the result's."""
    r = preston.solve(small_job, robust=True, rho=0.01, v_min=1.0)
    rob = r.report["robust"]
    assert rob["scenarios"][0] == "nominal" and len(rob["robust_plan_rms_nm"]) == 7
    assert rob["basis"] == "planned"
    # What it minimises: the mean over the scenarios of the squared residual.
    mean_sq = lambda v: sum(x * x for x in v) / len(v)  # noqa: E731
    assert mean_sq(rob["robust_plan_rms_nm"]) <= mean_sq(rob["nominal_plan_rms_nm"]) * 1.001
    assert abs(r.report["rms_after_nm"] - rob["robust_plan_rms_nm"][0]) <= 1e-9 * r.report["rms_after_nm"]
    assert "robust" not in preston.solve(small_job).report


def test_result_arrays_hold_the_figures_the_report_states(small_job):
    """Without and with an executed program, the result's residual, its grid and its dwell are
    the ones the report states (RMS and PV of ``residual_nm``, the grid's values, the total
    dwell), and the model's residual is the report's ``model`` where the program is executed."""
    for kw in ({}, {"a_max": 50.0}):
        r = preston.solve(small_job, **kw)
        rep = r.report
        e = r.residual_nm
        rms = float(np.sqrt(np.mean((e - e.mean()) ** 2)))
        assert abs(rms - rep["rms_after_nm"]) <= 1e-9 * rep["rms_before_nm"], kw
        assert abs(float(np.ptp(e)) - rep["pv_after_nm"]) <= 1e-9 * rep["pv_before_nm"], kw
        assert abs(float(r.dwell_s.sum()) - rep["total_dwell_s"]) <= 1e-9 * rep["total_dwell_s"], kw
        grid = r.residual_grid.values
        assert np.array_equal(np.sort(grid[~np.isnan(grid)]), np.sort(e)), kw
        if "model" in rep:
            m = r.model_residual_nm
            model_rms = float(np.sqrt(np.mean((m - m.mean()) ** 2)))
            assert abs(model_rms - rep["model"]["rms_nm"]) <= 1e-9 * rep["rms_before_nm"], kw
            assert rep["rms_after_nm"] == rep["executed"]["rms_after_nm"], kw
        else:
            np.testing.assert_array_equal(r.model_residual_nm, e)
