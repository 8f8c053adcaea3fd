"""Shared fixtures: the repository's sample data, the CLI binary, and a small synthetic job."""

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "data"


@pytest.fixture(scope="session")
def preston_bin() -> Path:
    """The `preston` CLI (PRESTON_BIN, else target/release/preston, built if missing)."""
    p = Path(os.environ.get("PRESTON_BIN", ROOT / "target" / "release" / "preston"))
    if not p.exists():
        subprocess.run(
            ["cargo", "build", "--release", "-p", "preston-cli"], cwd=ROOT, check=True
        )
    return p


@pytest.fixture(scope="session")
def sample_job() -> Path:
    return DATA / "job_point_1mm.toml"


def write_small_job(d: Path) -> dict:
    """A 24 x 16 mm map at 0.8 mm pitch (a smooth error, 40 to 140 nm) and a Gaussian TIF:
    a job dict that solves in well under a second."""
    xs = np.arange(0.0, 24.0 + 1e-9, 0.8)
    ys = np.arange(0.0, 16.0 + 1e-9, 0.8)
    x, y = (a.ravel() for a in np.meshgrid(xs, ys))
    z = 90.0 + 30.0 * np.cos(2 * np.pi * x / 24.0) + 20.0 * np.sin(2 * np.pi * y / 16.0)
    m = d / "small_map.csv"
    np.savetxt(m, np.column_stack([x, y, z]), delimiter=",", header="x_mm,y_mm,z_nm", comments="")
    return {
        "map": {"file": str(m)},
        "tif": {"gaussian": {"sigma_mm": 1.5, "peak_rate_nm_per_s": 20.0, "truncation_radius_mm": 4.5}},
        "dwell": {"raster_pitch_mm": 1.0},
        "machine": {"v_max_mm_per_min": 3000.0},
        "solver": {"solver": "qp", "influence": "point"},
    }


@pytest.fixture
def small_job(tmp_path: Path) -> dict:
    return write_small_job(tmp_path)
