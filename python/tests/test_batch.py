"""preston.batch on a 2-worker LocalCluster: results equal to one-by-one solves, failures
reported per job, outputs written atomically."""

import os
from pathlib import Path

import numpy as np
import pytest

import preston

distributed = pytest.importorskip("dask.distributed")


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
    )
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


def rows_of(table):
    return table.to_dict("records") if hasattr(table, "to_dict") else table


def test_grid_batch_equals_one_by_one(client, small_job, tmp_path):
    axes = {"machine.v_max_mm_per_min": [1500.0, 2000.0, 3000.0, 4000.0], "dwell.raster_pitch_mm": [1.0, 1.25]}
    jobs = preston.grid(small_job, axes, name="sweep")
    assert len(jobs) == 8
    bad = dict(small_job, name="broken", map={"file": str(tmp_path / "missing_map.csv")})
    out = tmp_path / "out"
    # An older result of one job is replaced whole.
    (out / "sweep-000").mkdir(parents=True)
    (out / "sweep-000" / "stale.txt").write_text("old")
    rows = rows_of(preston.batch(jobs + [bad], client=client, out_dir=out))
    assert [r["job"] for r in rows] == [f"sweep-{i:03d}" for i in range(8)] + ["broken"]
    for job, row in zip(jobs, rows[:8]):
        assert row["ok"], row["error"]
        assert row["machine.v_max_mm_per_min"] == job["machine"]["v_max_mm_per_min"]
        assert row["dwell.raster_pitch_mm"] == job["dwell"]["raster_pitch_mm"]
        one = preston.solve({k: v for k, v in job.items() if k != "name"})
        got = np.loadtxt(row["dwell_csv"], delimiter=",", skiprows=1)
        np.testing.assert_array_equal(got[:, 3], one.dwell_s)
        assert row["rms_after_nm"] == one.report["rms_after_nm"]
        assert row["total_dwell_s"] == one.report["total_dwell_s"]
        assert sorted(os.listdir(row["out_dir"])) == ["dwell.csv", "report.json", "residual.csv"]
    # Faster feeds allowed -> shorter or equal total dwell at the same pitch.
    for a, b in zip(rows[0:8:2], rows[2:8:2]):
        assert b["total_dwell_s"] <= a["total_dwell_s"] * (1 + 1e-9)
    broken = rows[8]
    # A missing file: the InputError that is also a FileNotFoundError.
    assert not broken["ok"] and broken["error_type"] == "InputFileNotFoundError"
    assert "missing_map.csv" in broken["error"]
    assert sorted(os.listdir(out)) == [f"sweep-{i:03d}" for i in range(8)]  # no temporary dirs


def test_job_files_default_cluster(small_job, tmp_path):
    """Job files from a directory, on the LocalCluster batch starts itself."""
    jobs_dir = tmp_path / "jobs"
    jobs_dir.mkdir()
    g = small_job["tif"]["gaussian"]
    for v in (2000, 3000):
        (jobs_dir / f"v{v}.toml").write_text(
            f'[map]\nfile = "{small_job["map"]["file"]}"\n'
            f'[tif]\ngaussian = {{ sigma_mm = {g["sigma_mm"]}, peak_rate_nm_per_s = {g["peak_rate_nm_per_s"]}, '
            f'truncation_radius_mm = {g["truncation_radius_mm"]} }}\n'
            f"[dwell]\nraster_pitch_mm = 1.0\n[machine]\nv_max_mm_per_min = {v}\n"
            '[solver]\nsolver = "qp"\n'
        )
    (jobs_dir / "typo.toml").write_text("[machine]\nvmax = 1\n")
    with pytest.raises(preston.InputError, match="vmax"):
        preston.batch(jobs_dir, out_dir=tmp_path / "out")
    (jobs_dir / "typo.toml").unlink()
    rows = rows_of(preston.batch(jobs_dir, out_dir=tmp_path / "out"))
    assert [r["job"] for r in rows] == ["v2000", "v3000"]
    for r in rows:
        assert r["ok"] and Path(r["job_file"]).parent == jobs_dir
        one = preston.solve(r["job_file"])
        got = np.loadtxt(r["dwell_csv"], delimiter=",", skiprows=1)
        np.testing.assert_array_equal(got[:, 3], one.dwell_s)


def test_threads_per_task(client):
    """Two single-thread workers on one host share its cores."""
    from preston._batch import threads_per_task

    assert threads_per_task(client) == max(1, (os.cpu_count() or 1) // 2)


def test_grid_needs_one_job(small_job):
    with pytest.raises(preston.InputError, match="one job"):
        preston.batch([small_job, small_job], grid={"machine.v_max_mm_per_min": [1000.0]})
    with pytest.raises(preston.InputError, match="list of values"):
        preston.grid(small_job, {"machine.v_max_mm_per_min": 1000.0})
