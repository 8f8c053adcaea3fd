"""TIF models and grids, paths, registration and program simulation: equal to the CLI's outputs
on the same inputs, closed forms where there are some, and their error paths."""

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

import preston

from conftest import DATA

#: Relative tolerance of values the CLI prints as JSON (shortest round-trip decimal: exact).
REL = 1e-12


def cli(preston_bin, *args, cwd=None):
    p = subprocess.run([str(preston_bin), *map(str, args)], capture_output=True, text=True, cwd=cwd)
    assert p.returncode == 0, p.stderr
    return p.stdout


def csv(path):
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def same_summary(py: dict, printed: str, skip=()):
    want = json.loads(printed)
    for k, v in want.items():
        if k in skip:
            continue
        assert k in py, k
        if isinstance(v, float):
            assert py[k] == pytest.approx(v, rel=REL, abs=0.0), k
        else:
            assert py[k] == v, k


def test_tif_models_equal_cli(preston_bin, tmp_path):
    out = tmp_path / "t.csv"
    cases = [
        (
            ["gaussian", "--sigma-mm", 1.5, "--peak-nm-per-s", 20, "--pitch-mm", 0.25],
            lambda: preston.tif_gaussian(1.5, 20.0, 0.25),
        ),
        (
            ["hertz", "--tool-e-gpa", 0.005, "--tool-nu", 0.4, "--part-e-gpa", 72, "--part-nu", 0.2,
             "--preston-k", 1e-7, "--pitch-mm", 0.1, "--part-radius-mm", 200],
            lambda: preston.tif_hertz(tool_e_gpa=0.005, tool_nu=0.4, part_e_gpa=72, part_nu=0.2,
                                      preston_k=1e-7, pitch_mm=0.1, part_radius_mm=200),
        ),
        (
            ["hertz", "--tool-e-gpa", 0.005, "--tool-nu", 0.4, "--part-e-gpa", 72, "--part-nu", 0.2,
             "--preston-k", 1e-7, "--pitch-mm", 0.1, "--surface", DATA / "design_freeform.json", "--at-mm", "5,-3"],
            lambda: preston.tif_hertz(tool_e_gpa=0.005, tool_nu=0.4, part_e_gpa=72, part_nu=0.2,
                                      preston_k=1e-7, pitch_mm=0.1,
                                      surface=DATA / "design_freeform.json", at_mm=(5, -3)),
        ),
        (
            ["bonnet", "--bonnet-radius-mm", 20, "--depth-mm", 0.3, "--force-n", 10, "--preston-k", 1e-7,
             "--pitch-mm", 0.2, "--azimuths", 4],
            lambda: preston.tif_bonnet(bonnet_radius_mm=20, depth_mm=0.3, force_n=10, preston_k=1e-7,
                                       pitch_mm=0.2, azimuths=4),
        ),
        (
            ["grid", "--in", DATA / "tif_fluid_jet_10mm.csv", "--pitch-mm", 0.3, "--recentre",
             "--peak-nm-per-s", 50],
            lambda: preston.tif_grid(csv(DATA / "tif_fluid_jet_10mm.csv"), pitch_mm=0.3, recentre=True,
                                     peak_nm_per_s=50.0),
        ),
    ]
    for args, py in cases:
        printed = cli(preston_bin, "tif", *args, "--out", out)
        xyr, summary = py()
        np.testing.assert_array_equal(xyr, csv(out))
        same_summary(summary, printed)


def test_gaussian_tif_closed_form():
    """Samples of the truncated Gaussian; volume 2 pi sigma^2 peak (1 - exp(-t^2 / (2 sigma^2)))."""
    sigma, peak, pitch = 1.2, 30.0, 0.2
    xyr, s = preston.tif_gaussian(sigma, peak, pitch)
    rho2 = xyr[:, 0] ** 2 + xyr[:, 1] ** 2
    inside = rho2 <= (3 * sigma) ** 2 * (1 - 1e-12)
    np.testing.assert_allclose(xyr[inside, 2], peak * np.exp(-rho2[inside] / (2 * sigma**2)), rtol=1e-12)
    assert s["peak_rate_nm_per_s"] == pytest.approx(peak, rel=1e-12)
    vol = 2 * np.pi * sigma**2 * peak * (1 - np.exp(-4.5)) * 1e-6 * 60  # nm mm^2/s -> mm^3/min
    assert s["volume_rate_mm3_per_min"] == pytest.approx(vol, rel=1e-9)
    # The solver takes the grid as it is.
    assert preston.tif_grid(xyr)[0].shape == xyr.shape


def test_tif_spot_equals_cli_and_recovers_the_gaussian(preston_bin, tmp_path):
    """A 10 s spot of a known Gaussian on a tilted part: the TIF comes back, as from the CLI."""
    xs = np.arange(-10.0, 10.0 + 1e-9, 0.25)
    x, y = (a.ravel() for a in np.meshgrid(xs, xs))
    before = 50.0 + 0.8 * x - 0.3 * y
    sigma, peak, dwell = 1.5, 20.0, 10.0
    after = before - dwell * peak * np.exp(-((x - 0.5) ** 2 + (y + 0.25) ** 2) / (2 * sigma**2))
    for name, z in (("before", before), ("after", after)):
        np.savetxt(tmp_path / f"{name}.csv", np.column_stack([x, y, z]), delimiter=",",
                   header="x_mm,y_mm,z_nm", comments="")
    printed = cli(preston_bin, "tif", "spot", "--before", tmp_path / "before.csv", "--after", tmp_path / "after.csv",
                  "--dwell-s", dwell, "--remove", "piston,tilt", "--fit", "gaussian", "--out", tmp_path / "t.csv")
    xyr, s = preston.tif_spot((x, y, before), (x, y, after), dwell, remove_tilt=True, fit="gaussian")
    np.testing.assert_array_equal(xyr, csv(tmp_path / "t.csv"))
    same_summary(s, printed)
    assert s["gaussian_peak_nm_per_s"] == pytest.approx(peak, rel=1e-3)
    assert s["sigma_x_mm"] == pytest.approx(sigma, rel=1e-3)
    assert s["spot_centroid_mm"] == pytest.approx([0.5, -0.25], abs=1e-3)


def test_paths_equal_cli(preston_bin, tmp_path):
    out = tmp_path / "p.csv"
    cli(preston_bin, "path", "spiral", "--radius-mm", 20, "--pitch-mm", 2, "--step-mm", 1.5, "--centre-mm", "1,-2",
        "--out", out)
    x, y = preston.path_spiral(20.0, 2.0, 1.5, centre_mm=(1.0, -2.0))
    np.testing.assert_array_equal(np.column_stack([x, y]), csv(out)[:, :2])
    # Archimedes: r = pitch theta / (2 pi) grows by the pitch per turn; it ends on the radius.
    assert np.hypot(x[-1] - 1.0, y[-1] + 2.0) == pytest.approx(20.0, rel=1e-12)

    printed = cli(preston_bin, "path", "random", "--x-mm", "0,20", "--y-mm", "0,10", "--pitch-mm", 1, "--seed", 7,
                  "--jitter", 0.3, "--out", out)
    x, y, s = preston.path_random((0, 20), (0, 10), 1.0, seed=7, jitter=0.3)
    np.testing.assert_array_equal(np.column_stack([x, y]), csv(out)[:, :2])
    same_summary(s, printed, skip=("length_mm",))  # the CLI's sum of ds_mm over the written path
    assert len(x) == s["points"] and x.min() >= 0 and x.max() <= 20 and y.min() >= 0 and y.max() <= 10

    printed = cli(preston_bin, "path", "edge-offset", "--edge-radius-mm", 50, "--bonnet-radius-mm", 20,
                  "--spot-max-mm", 6, "--spot-min-mm", 1.5, "--ratio", 0.8, "--residual-um", 1, "--out", out)
    x, y, s = preston.path_edge_offset(edge_radius_mm=50, bonnet_radius_mm=20, spot_max_mm=6, spot_min_mm=1.5,
                                       ratio=0.8, residual_um=1.0)
    np.testing.assert_array_equal(np.column_stack([x, y]), csv(out)[:, :2])
    same_summary(s, printed)
    assert np.hypot(x, y).max() < 50.0


def test_workflow_errors(small_job):
    with pytest.raises(preston.InputError, match="sigma"):
        preston.tif_gaussian(-1.0, 20.0, 0.25)
    with pytest.raises(preston.InputError, match="nu"):
        preston.tif_hertz(tool_e_gpa=0.005, tool_nu=0.7, part_e_gpa=72, part_nu=0.2, preston_k=1e-7, pitch_mm=0.1)
    with pytest.raises(preston.InputError, match="at_mm"):
        preston.tif_hertz(tool_e_gpa=0.005, tool_nu=0.4, part_e_gpa=72, part_nu=0.2, preston_k=1e-7, pitch_mm=0.1,
                          surface=DATA / "design_freeform.json")
    with pytest.raises(preston.InputError, match="depth"):
        preston.tif_bonnet(bonnet_radius_mm=20, depth_mm=25, force_n=10, preston_k=1e-7, pitch_mm=0.2)
    with pytest.raises(preston.InputError, match="not both"):
        preston.tif_grid(preston.tif_gaussian(1.0, 1.0, 0.2)[0], peak_nm_per_s=1.0, volume_mm3_per_min=1.0)
    with pytest.raises(preston.InputError, match=r"\(N, 3\)"):
        preston.tif_grid(np.zeros((5, 2)))
    with pytest.raises(preston.InputError, match="dwell"):
        preston.tif_spot(np.zeros((4, 3)), np.zeros((4, 3)), -1.0)
    with pytest.raises(preston.InputError, match="pitch"):
        preston.path_spiral(20.0, -2.0)
    with pytest.raises(preston.InputError, match="jitter"):
        preston.path_random((0, 10), (0, 10), 1.0, jitter=2.0)
    with pytest.raises(preston.InputError, match="ratio= or decrement_mm="):
        preston.path_edge_offset(edge_radius_mm=50, bonnet_radius_mm=20, spot_max_mm=6, spot_min_mm=1.5,
                                 residual_um=1.0)
    with pytest.raises(preston.InputError, match="spot"):
        preston.path_edge_offset(edge_radius_mm=50, bonnet_radius_mm=20, spot_max_mm=1, spot_min_mm=1.5,
                                 ratio=0.8, residual_um=1.0)
    with pytest.raises(preston.InputError, match="nowhere.json"):
        preston.register(Path("nowhere.json"), np.zeros((10, 3)))
    with pytest.raises(preston.InputError, match="qx"):
        preston.register({"type": "plane"}, np.zeros((10, 3)), lock=["qx"])


def plane_points(tilt=1e-4, piston_mm=5e-3):
    g = np.linspace(-20.0, 20.0, 9)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    return np.column_stack([x, y, tilt * x + piston_mm])


def test_register_plane_closed_form_and_undetermined():
    """Points on a tilted, raised plane: M takes them back onto z = 0 (ry = atan(tilt), tz =
    -piston), no form error. Without locks a plane leaves rz, tx, ty free: refused."""
    pts = plane_points()
    with pytest.raises(preston.InputError, match="do not determine"):
        preston.register({"type": "plane"}, pts)
    r = preston.register({"type": "plane"}, pts, lock=["rz", "tx", "ty"])
    t = r["transform"]
    assert t["converged"]
    assert abs(t["rotation_arcsec"][1]) == pytest.approx(np.degrees(np.arctan(1e-4)) * 3600, rel=1e-6)
    assert np.max(np.abs(r["form_error_nm"])) < 1e-6
    np.testing.assert_allclose(r["points_xyz_mm"][:, 2], 0.0, atol=1e-12)
    assert r["points_xyz_mm"].shape == pts.shape and r["weights"].shape == (len(pts),)


def test_register_equals_cli(preston_bin, tmp_path):
    """Points off the freeform design by a piston, a tilt and a smooth wave, Huber-weighted,
    in-plane motions held: transform.json, form_error.csv and registered_points.csv as the CLI
    writes them."""
    surface = DATA / "design_freeform.json"
    g = np.linspace(-20.0, 20.0, 11)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    pts = np.column_stack([x, y, 0.002 * np.cos(x / 7.0) + 1e-5 * y])
    pfile = tmp_path / "p.csv"
    np.savetxt(pfile, pts, delimiter=",", header="x_mm,y_mm,z_mm", comments="")
    out = tmp_path / "reg"
    cli(preston_bin, "register", "--surface", surface, "--points", pfile, "--lock", "rz,tx,ty",
        "--robust", "huber", "--out", out)
    r = preston.register(surface, pts, lock=["rz", "tx", "ty"], robust="huber")
    want = json.loads((out / "transform.json").read_text())
    assert set(r["transform"]) == set(want)
    for k in ("rotation_arcsec", "translation_um", "dof_sigma", "information_eigenvalues"):
        np.testing.assert_allclose(r["transform"][k], want[k], rtol=REL, atol=1e-15)
    assert r["transform"]["rms_nm"] == pytest.approx(want["rms_nm"], rel=REL)
    assert r["transform"]["iterations"] == want["iterations"]
    fe = csv(out / "form_error.csv")
    np.testing.assert_array_equal(np.column_stack([r["design_x_mm"], r["design_y_mm"], r["form_error_nm"]]), fe)
    rp = csv(out / "registered_points.csv")
    np.testing.assert_array_equal(np.column_stack([r["points_xyz_mm"], r["weights"]]), rp)


def program_simulated_by_cli(preston_bin, small_job, tmp_path, *extra):
    """The small job solved, its program written to `p.nc` and run by `preston simulate --program`
    with `extra` flags into `sim`: (program, the job's Gaussian, the output folder)."""
    r = preston.solve(small_job)
    program = tmp_path / "p.nc"
    program.write_text(preston.nc(np.column_stack([r.dwell_x_mm, r.dwell_y_mm]), r.dwell_s))
    g = small_job["tif"]["gaussian"]
    out = tmp_path / "sim"
    cli(preston_bin, "simulate", "--map", small_job["map"]["file"], "--gaussian-sigma-mm", g["sigma_mm"],
        "--gaussian-peak-nm-per-s", g["peak_rate_nm_per_s"], "--gaussian-truncation-mm", g["truncation_radius_mm"],
        "--program", program, *extra, "--out", out)
    return program, g, out


def test_simulate_program_on_a_curved_part_equals_cli(preston_bin, small_job, tmp_path):
    """On a sphere each contact sample applies the TIF in its tangent frame, as `preston simulate
    --program --surface` does; the same program taken as flat leaves another removal, and an
    unknown frame is an input error."""
    surface = {"type": "conic", "curvature_per_mm": 1.0 / 40.0}
    surface_file = tmp_path / "sphere.json"
    surface_file.write_text(json.dumps(surface))
    program, g, out = program_simulated_by_cli(preston_bin, small_job, tmp_path, "--surface", surface_file)
    s = preston.simulate_program(small_job["map"]["file"], program, gaussian=g, surface=surface)
    res = csv(out / "residual.csv")
    np.testing.assert_array_equal(
        np.column_stack([s["map_x_mm"], s["map_y_mm"], s["z_nm"], s["removal_nm"], s["residual_nm"]]), res
    )
    flat = preston.simulate_program(small_job["map"]["file"], program, gaussian=g)
    assert not np.allclose(flat["removal_nm"], s["removal_nm"], rtol=1e-3)
    assert set(s["report"]["sensitivity"]) == {
        "tif_wider_3pct", "tif_narrower_3pct", "rate_plus_3pct", "offset_x_0p05mm", "offset_y_0p05mm"}
    with pytest.raises(preston.InputError, match="tif_frame"):
        preston.simulate_program(small_job["map"]["file"], program, gaussian=g, surface=surface,
                                 tif_frame="sideways")


def test_simulate_program_equals_cli(preston_bin, small_job, tmp_path):
    """A solved plan turned into G-code, run with a 500 mm/s^2 acceleration limit: removal and
    report as `preston simulate --program --a-max-mm-per-s2`; the programmed-feed run delivers the
    plan (executed = planned dwell) and the accelerated one takes longer."""
    program, g, out = program_simulated_by_cli(preston_bin, small_job, tmp_path, "--a-max-mm-per-s2", 500)
    events = []
    s = preston.simulate_program(small_job["map"]["file"], program, gaussian=g, a_max_mm_per_s2=500.0,
                                 progress=events.append)
    res = csv(out / "residual.csv")
    np.testing.assert_array_equal(
        np.column_stack([s["map_x_mm"], s["map_y_mm"], s["z_nm"], s["removal_nm"], s["residual_nm"]]), res
    )
    want = json.loads((out / "report.json").read_text())
    for k in ("rms_before_nm", "rms_after_nm", "pv_after_nm", "total_dwell_s"):
        assert s["report"][k] == pytest.approx(want[k], rel=REL), k
    assert events and {e["stage"] for e in events} <= {"assembly", "solve", "loop"}
    plain = preston.simulate_program(small_job["map"]["file"], program, gaussian=g)
    c = plain["check"]
    assert c["executed_total_s"] == pytest.approx(c["planned_total_s"], rel=1e-6)
    assert s["check"]["executed_total_s"] > c["executed_total_s"]
    with pytest.raises(preston.InputError, match="a_max_mm_per_s2"):
        preston.simulate_program(small_job["map"]["file"], program, gaussian=g, a_max_mm_per_s2=-1.0)
    with pytest.raises(preston.InputError, match="missing.nc"):
        preston.simulate_program(small_job["map"]["file"], tmp_path / "missing.nc", gaussian=g)
    with pytest.raises(preston.InputError, match="one of"):
        preston.simulate_program(small_job["map"]["file"], program)


def test_iterate_equals_cli(preston_bin, tmp_path):
    """Two runs of the virtual loop (tilted installation, measurement noise, TIF rate error):
    convergence.csv, final_measured.csv and the last run's dwell.csv as the CLI writes them;
    the error falls run by run. A real part's map plans one run; bad settings are named."""
    args = dict(gaussian={"sigma_mm": 2.0, "peak_rate_nm_per_s": 20.0, "truncation_radius_mm": 6.0},
                grid=(21, 21), aperture_x_mm=(-10, 10), aperture_y_mm=(-10, 10), iterations=2,
                rotation_arcsec=(5, 0, 0), noise_nm=1.0, tif_rate_error=0.03)
    out = tmp_path / "it"
    cli(preston_bin, "iterate", "--gaussian-sigma-mm", 2, "--gaussian-peak-nm-per-s", 20, "--gaussian-truncation-mm", 6,
        "--grid", "21,21", "--aperture-x-mm=-10,10", "--aperture-y-mm=-10,10", "--iterations", 2,
        "--rotation-arcsec", "5,0,0", "--noise-nm", 1, "--tif-rate-error", 0.03, "--out", out)
    r = preston.iterate(**args)
    conv = np.genfromtxt(out / "convergence.csv", delimiter=",", names=True)
    assert len(r["records"]) == len(conv) == 3
    for rec, row in zip(r["records"], conv):
        for k in ("iteration", "pv_nm", "rms_nm", "max_abs_nm", "mean_abs_nm", "time_s"):
            assert rec[k] == pytest.approx(row[k], rel=REL, abs=0.0), k
    assert r["records"][2]["rms_nm"] < r["records"][1]["rms_nm"] < r["records"][0]["rms_nm"]
    np.testing.assert_array_equal(np.column_stack(r["final_measured"]), csv(out / "final_measured.csv"))
    d = csv(out / "dwell.csv")
    last = r["last_run"]
    np.testing.assert_array_equal(np.column_stack([last["dwell_x_mm"], last["dwell_y_mm"]]), d[:, :2])
    np.testing.assert_array_equal(last["dwell_s"], d[:, 3])
    assert not r["not_converged"] and not r["met_spec"]

    # One run on a measured map (here the loop's own last measurement).
    events = []
    plan = preston.iterate(gaussian=args["gaussian"], map_xyz=r["final_measured"], iteration=2, threads=1,
                           progress=events.append)
    assert plan["last_run"] is not None and len(plan["last_run"]["dwell_s"]) > 0
    assert plan["records"][0]["predicted_rms_nm"] < plan["records"][0]["rms_nm"]
    assert events

    with pytest.raises(preston.InputError, match="grid"):
        preston.iterate(gaussian=args["gaussian"], grid=(1, 21))
    with pytest.raises(preston.InputError, match="one of"):
        preston.iterate()
