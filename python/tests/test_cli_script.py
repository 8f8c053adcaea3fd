"""The wheel's `preston` console script (the binary's code, run by the installed package) and the
sample job shipped inside the package (`preston sample`, `preston.sample_job`)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import preston

from conftest import DATA

SAMPLE_FILES = ("job.toml", "mirror_error_118x8mm.csv", "tif_fluid_jet_10mm.csv", "README.md")


def script() -> Path:
    """The `preston` command pip installed beside this interpreter (the wheel's console script)."""
    p = Path(sys.executable).parent / ("preston.exe" if os.name == "nt" else "preston")
    assert p.exists(), f"no console script {p}: is the wheel installed in this environment?"
    return p


def run(*args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([str(script()), *map(str, args)], capture_output=True, text=True, **kw)


@pytest.fixture(scope="module")
def checkout_sample(tmp_path_factory) -> Path:
    """The sample job of the checkout (data/job.toml) solved by the Python API: its output
    directory (dwell.csv, residual.csv, report.json)."""
    out = tmp_path_factory.mktemp("checkout") / "out"
    preston.solve(DATA / "job.toml").write(out)
    return out


def test_the_console_script_is_the_command_line_of_the_same_version():
    r = run("--version")
    assert r.returncode == 0, r.stderr
    assert r.stdout == f"preston {preston.__version__}\n"
    r = run("--help")
    assert r.returncode == 0 and "Usage: preston" in r.stdout, r.stderr
    for sub in ("solve", "sample", "simulate", "nc"):
        assert f"\n  {sub} " in r.stdout, sub


def test_the_console_script_solves_the_shipped_sample_as_the_checkout_solves_data_job(
    tmp_path, checkout_sample
):
    r = run("sample", "--out", tmp_path / "sample")
    assert r.returncode == 0, r.stderr
    job = Path(r.stdout.strip())
    assert job == tmp_path / "sample" / "job.toml"
    out = tmp_path / "out"
    # Run from elsewhere: the job's files are found relative to the job, not the working directory.
    r = run("solve", "--job", job, "--out", out, "--json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    summary = preston_json(r.stdout)
    assert summary["converged"] is True and summary["exit_code"] == 0, summary
    assert summary["report"]["status"] == "converged", summary
    for name in ("dwell.csv", "residual.csv", "report.json"):
        assert (out / name).is_file(), name
    # The same plan as the checkout's data/job.toml (the same inputs, byte for byte).
    for name in ("dwell.csv", "residual.csv"):
        assert (out / name).read_bytes() == (checkout_sample / name).read_bytes(), name


def preston_json(stdout: str) -> dict:
    import json

    lines = stdout.strip().splitlines()
    assert len(lines) == 1, stdout
    return json.loads(lines[0])


def test_exit_codes_are_the_binarys(tmp_path):
    # Bad input: exit 2 and a message naming the file.
    missing = tmp_path / "no_such_job.toml"
    r = run("solve", "--job", missing, "--out", tmp_path / "o1")
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("error: ") and "no_such_job.toml" in r.stderr, r.stderr
    # A usage error: clap's exit 2.
    r = run("solve", "--no-such-flag")
    assert r.returncode == 2 and "--no-such-flag" in r.stderr, r.stderr
    # Not converged: exit 3, the outputs written with their status.
    out = tmp_path / "o3"
    r = run("solve", "--job", DATA / "job_point_1mm.toml", "--max-iterations", "2", "--out", out)
    assert r.returncode == 3, r.stderr
    assert "did not converge" in r.stderr, r.stderr
    assert (out / "report.json").is_file()


def test_a_closed_pipe_is_not_an_error():
    # `preston completions bash | head -1`: the reader goes after one line.
    p = subprocess.Popen(
        [str(script()), "completions", "bash"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    first = p.stdout.readline()
    p.stdout.close()
    _, err = p.communicate(timeout=60)
    assert first, "no output"
    assert p.returncode == 0, err
    assert b"error" not in err.lower() and b"panic" not in err.lower(), err


def test_sample_job_writes_the_checkout_data_and_solves_as_data_job(tmp_path, checkout_sample):
    job = preston.sample_job(tmp_path / "s")
    assert job == tmp_path / "s" / "job.toml"
    for name in SAMPLE_FILES:
        assert (tmp_path / "s" / name).read_bytes() == (DATA / name).read_bytes(), name
    r = preston.solve(job)
    assert r.converged
    out = tmp_path / "out"
    r.write(out)
    assert (out / "dwell.csv").read_bytes() == (checkout_sample / "dwell.csv").read_bytes()
    expected = np.loadtxt(checkout_sample / "dwell.csv", delimiter=",", skiprows=1)
    assert expected.shape[0] == r.dwell_s.size


def test_sample_job_writes_over_files_only_when_asked(tmp_path):
    d = tmp_path / "s"
    d.mkdir()
    (d / "job.toml").write_text("mine")
    with pytest.raises(preston.InputError, match="job.toml: already exists"):
        preston.sample_job(d)
    # Nothing written.
    assert sorted(p.name for p in d.iterdir()) == ["job.toml"]
    assert (d / "job.toml").read_text() == "mine"
    r = run("sample", "--out", d)
    assert r.returncode == 2 and "--force" in r.stderr, r.stderr
    assert preston.sample_job(d, overwrite=True) == d / "job.toml"
    assert (d / "job.toml").read_bytes() == (DATA / "job.toml").read_bytes()
    r = run("sample", "--out", d, "--force")
    assert r.returncode == 0, r.stderr


def test_the_wheel_declares_the_console_script_and_the_scipy_extra():
    from importlib import metadata

    dist = metadata.distribution("preston-dwell")
    scripts = {e.name: e.value for e in dist.entry_points if e.group == "console_scripts"}
    assert scripts == {"preston": "preston._cli:main"}
    assert "scipy" in (dist.metadata.get_all("Provides-Extra") or [])
    requires = dist.metadata.get_all("Requires-Dist") or []
    norm = [r.replace(" ", "").replace('"', "'") for r in requires]
    assert any(r.startswith("scipy") and "extra=='scipy'" in r for r in norm), requires


def test_influence_matrix_without_scipy_names_the_extra(monkeypatch, small_job):
    # As in an environment without scipy: importing it fails.
    monkeypatch.setitem(sys.modules, "scipy", None)
    monkeypatch.setitem(sys.modules, "scipy.sparse", None)
    with pytest.raises(ImportError, match=r"pip install 'preston-dwell\[scipy\]'"):
        preston.influence_matrix(small_job)
