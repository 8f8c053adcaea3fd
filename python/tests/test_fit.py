"""preston.fit recovers a known surface (sag of a sphere plus a polynomial term)."""

import numpy as np
import pytest

import preston


def test_fit_recovers_a_known_surface():
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-20, 20, 400), rng.uniform(-20, 20, 400)
    c = 1.0 / 500.0  # curvature, 1/mm
    r2 = x * x + y * y
    z = c * r2 / (1 + np.sqrt(1 - c * c * r2)) + 2e-6 * x * y  # sphere sag + 2 nm/mm^2 * xy
    surface, summary, residual = preston.fit((x, y, z), order=4, curvature_per_mm=c)
    assert summary["points"] == 400
    # The polynomial spans x*y: the residual is at the level of rounding (nm).
    assert summary["rms_nm"] < 1e-3 and np.max(np.abs(residual)) < 1e-2
    assert residual.dtype == np.float64 and residual.shape == (400,)
    assert isinstance(surface, dict) and surface
    with pytest.raises(preston.InputError):
        preston.fit((x[:3], y[:3], z[:3]), order=4, curvature_per_mm=c)
