""""A dwell file or a raster, not both": every face (the CLI's flags, a job file, the Python
keywords, a job dict and a batch) refuses the pair with the one message the engine writes."""

import subprocess
from pathlib import Path

import numpy as np
import pytest

import preston


def cli_message(preston_bin, tmp_path, job_path, dwell):
    """The CLI's message for a dwell file and a raster pitch given together as flags."""
    out = subprocess.run(
        [str(preston_bin), "solve", "--job", str(job_path), "--dwell", str(dwell),
         "--raster-pitch-mm", "1.0", "--out", str(tmp_path / "cli")],
        capture_output=True, text=True,
    )
    assert out.returncode == 2, out.stderr
    line = out.stderr.strip().splitlines()[-1]
    # "error: <command line>: MESSAGE"
    return line.rsplit(": ", 1)[-1]


def test_every_face_refuses_a_dwell_file_and_a_raster_with_one_message(preston_bin, small_job, tmp_path):
    dwell = tmp_path / "d.csv"
    np.savetxt(dwell, [[4.0, 4.0], [5.0, 4.0]], delimiter=",", header="x_mm,y_mm", comments="")
    job_path = tmp_path / "job.toml"
    job_path.write_text(
        f"[map]\nfile = {str(small_job['map']['file'])!r}\n"
        "[tif]\ngaussian = { sigma_mm = 1.5, peak_rate_nm_per_s = 20.0, truncation_radius_mm = 4.5 }\n"
        "[dwell]\nraster_pitch_mm = 1.0\n[machine]\nv_max_mm_per_min = 3000.0\n"
    )
    message = cli_message(preston_bin, tmp_path, job_path, dwell)
    assert "not both" in message

    # A job file naming both.
    both_toml = tmp_path / "both.toml"
    both_toml.write_text(job_path.read_text().replace("raster_pitch_mm = 1.0", f"raster_pitch_mm = 1.0\nfile = {str(dwell)!r}"))
    with pytest.raises(preston.InputError) as e:
        preston.solve(both_toml)
    assert message in str(e.value)
    out = subprocess.run(
        [str(preston_bin), "solve", "--job", str(both_toml), "--out", str(tmp_path / "cli2")],
        capture_output=True, text=True,
    )
    assert out.returncode == 2 and message in out.stderr, out.stderr

    # The Python keywords, on a job with a raster and on one without.
    with pytest.raises(preston.InputError) as e:
        preston.solve(small_job, dwell=dwell, raster_pitch_mm=1.0)
    assert message in str(e.value)
    no_dwell = {k: v for k, v in small_job.items() if k != "dwell"}
    with pytest.raises(preston.InputError) as e:
        preston.solve(no_dwell, dwell_xy=[[4.0, 4.0], [5.0, 4.0]], raster_pitch_mm=1.0)
    assert message in str(e.value)

    # A job dict naming both, alone and in a batch.
    both = dict(small_job, dwell={"file": str(dwell), "raster_pitch_mm": 1.0})
    with pytest.raises(preston.InputError) as e:
        preston.solve(both)
    assert message in str(e.value)
    with pytest.raises(preston.InputError) as e:
        preston.batch([both], out_dir=tmp_path / "batch")
    assert message in str(e.value)


def test_a_grid_over_the_dwell_source_replaces_the_jobs_source(small_job, tmp_path):
    dwell = tmp_path / "d.csv"
    np.savetxt(dwell, [[4.0, 4.0], [5.0, 4.0]], delimiter=",", header="x_mm,y_mm", comments="")
    jobs = preston.grid(small_job, {"dwell.file": [str(dwell)]})
    assert jobs[0]["dwell"].get("file") == str(dwell)
    assert jobs[0]["dwell"].get("raster_pitch_mm") is None
    job = {k: v for k, v in jobs[0].items() if k != "name"}  # grid names its jobs for batch
    back = preston.grid(job, {"dwell.raster_pitch_mm": [0.8]})
    assert back[0]["dwell"].get("raster_pitch_mm") == 0.8
    assert back[0]["dwell"].get("file") is None


def test_the_machine_keywords_docstring_names_every_choice_the_cli_offers(preston_bin, sample_job):
    """``preston.solve``'s docstring names each ``accel_method`` the CLI's flag accepts (the
    clap definition lists them from the library's enum), the sample job's among them."""
    import re

    text = subprocess.run(
        [str(preston_bin), "solve", "--help"], capture_output=True, text=True, check=True
    ).stdout
    section = text[text.index("--accel-method"):]
    section = section[section.index("Possible values:"):]
    values = re.findall(r"^\s+- ([a-z-]+):", section, flags=re.M)
    values = values[: values.index("correction-passes") + 1] if "correction-passes" in values else values
    assert "correction-passes" in values, section[:400]
    doc = preston.solve.__doc__
    for v in values:
        assert f'"{v}"' in doc, v
    job = preston.load_job(Path(__file__).resolve().parents[2] / "data" / "job.toml")
    assert job["machine"]["accel_method"] in values
