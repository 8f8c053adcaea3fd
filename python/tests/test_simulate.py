"""preston.simulate and preston.raster against the solver's own model."""

import numpy as np
import pytest

import preston


def test_discrete_simulation_is_the_solvers_removal(small_job):
    r = preston.solve(small_job)
    xyz = (r.map_x_mm, r.map_y_mm, r.z_nm)
    pts = np.column_stack([r.dwell_x_mm, r.dwell_y_mm])
    removal, residual = preston.simulate(xyz, pts, r.dwell_s, gaussian=small_job["tif"]["gaussian"])
    np.testing.assert_allclose(removal, r.removal_nm, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(residual, r.residual_nm, rtol=1e-12, atol=1e-9)
    # Sweeping instead of dwelling moves removal but keeps the total volume within a few percent.
    swept, _ = preston.simulate(xyz, pts, r.dwell_s, gaussian=small_job["tif"]["gaussian"], samples_per_point=8)
    assert swept.sum() == pytest.approx(removal.sum(), rel=0.05)
    with pytest.raises(preston.InputError, match="dwell_s"):
        preston.simulate(xyz, pts, r.dwell_s[:-1], gaussian=small_job["tif"]["gaussian"])


def test_raster_is_the_solvers_path(small_job):
    r = preston.solve(small_job)
    # The map's box extended by the TIF's nominal radius (the truncation radius of a Gaussian),
    # its lower corner moved down onto the map's 0.8 mm lattice (report.json raster).
    ext = small_job["tif"]["gaussian"]["truncation_radius_mm"]
    lo = np.floor((0.0 - ext) / 0.8 + 1e-6) * 0.8
    assert r.report["raster"]["phase_cells"] == [0.0, 0.0]
    assert r.report["raster"]["origin_mm"] == pytest.approx([lo, lo], abs=1e-9)
    # The lattice's pitch as the solver finds it (the smallest step between map coordinates).
    ox, oy = r.report["raster"]["origin_mm"]
    x, y = preston.raster((ox, 24.0 + ext), (oy, 16.0 + ext), 1.0, "x")
    np.testing.assert_array_equal(x, r.dwell_x_mm)
    np.testing.assert_array_equal(y, r.dwell_y_mm)
    with pytest.raises(preston.InputError, match="pitch"):
        preston.raster((0, 1), (0, 1), -1.0)
