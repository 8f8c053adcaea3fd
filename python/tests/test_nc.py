"""preston.nc writes the CLI's program for the same plan."""

import subprocess

import numpy as np
import pytest

import preston


def test_nc_equals_cli(preston_bin, small_job, tmp_path):
    r = preston.solve(small_job)
    r.write(tmp_path)
    out = tmp_path / "program.nc"
    subprocess.run(
        [str(preston_bin), "nc", "--dwell", str(tmp_path / "dwell.csv"), "--v-max", "3000", "--out", str(out)],
        check=True,
        capture_output=True,
    )
    pts = np.column_stack([r.dwell_x_mm, r.dwell_y_mm])
    text = preston.nc(pts, r.dwell_s, v_max_mm_per_min=3000.0,
                      notes=["INPUT DWELL FILE dwell.csv", "SURFACE FLAT Z = 0"])
    assert text == out.read_text()
    with pytest.raises(preston.InputError, match="dialekt"):
        preston.nc(pts, r.dwell_s, dialekt="iso")
