"""docs/tutorial.py runs from the measured map to the program, the plots and the report, and its
2-D PSD agrees with numpy's FFT estimate of the same map."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

#: Agreement of psd_2d.csv with the independent numpy estimate, relative.
PSD_REL_TOL = 0.05


def load_tutorial():
    spec = importlib.util.spec_from_file_location("tutorial", ROOT / "docs" / "tutorial.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_tutorial_runs_end_to_end(tmp_path):
    out = load_tutorial().main(str(tmp_path))
    for f in ("report.html", "report.json", "residual.png", "psd_2d.csv", "program.nc"):
        assert (tmp_path / f).is_file(), f
    report = json.loads((tmp_path / "report.json").read_text())
    html = (tmp_path / "report.html").read_text()
    for key in ("rms_before_nm", "pv_after_nm", "total_dwell_s"):
        assert f'data-key="{key}" data-value="{report[key]!r}"' in html, key
    assert out["R"].shape == (out["result"].z_nm.size, out["result"].dwell_s.size)
    assert out["executed"]["check"]["max_relative_error"] < 0.05

    # psd_2d.csv against numpy: the same windowed periodogram from the error grid.
    rows = np.loadtxt(tmp_path / "psd_2d.csv", delimiter=",", skiprows=1)
    g = out["result"].error_grid
    ny, nx = g.values.shape
    pitch = g.x_mm[1] - g.x_mm[0]
    measured = np.isfinite(g.values)
    mean = g.values[measured].mean()
    hann = lambda n: np.sin(np.pi * (np.arange(n) + 0.5) / n) ** 2  # noqa: E731
    w = np.outer(hann(ny), hann(nx)) * measured
    zw = np.where(measured, g.values - mean, 0.0) * w
    u = (w**2).sum() / (nx * ny)
    psd = np.fft.fftshift(np.abs(np.fft.fft2(zw)) ** 2) * pitch**2 / (nx * ny * u)
    fx = np.fft.fftshift(np.fft.fftfreq(nx, pitch))
    fy = np.fft.fftshift(np.fft.fftfreq(ny, pitch))
    ours = rows[:, 2].reshape(ny, nx)
    np.testing.assert_allclose(rows[:nx, 0], fx, atol=1e-12)
    np.testing.assert_allclose(rows[::nx, 1], fy, atol=1e-12)
    big = psd > 1e-9 * psd.max()
    assert big.sum() > 50
    assert np.max(np.abs(ours[big] / psd[big] - 1.0)) < PSD_REL_TOL
