"""preston.read_map: the CLI's readers and options, arrays out."""

import numpy as np
import pytest

import preston

from conftest import DATA


def test_csv_equals_the_file():
    x, y, z = preston.read_map(DATA / "mirror_error_118x8mm.csv")
    ref = np.loadtxt(DATA / "mirror_error_118x8mm.csv", delimiter=",", skiprows=1)
    for got, col in ((x, 0), (y, 1), (z, 2)):
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got, ref[:, col])


def test_npy_grid_placement_and_units(tmp_path):
    """Pixel (i, j) at x = (j - (nx-1)/2) p, y = ((ny-1)/2 - i) p; heights in um -> nm."""
    a = np.arange(12, dtype=np.float64).reshape(3, 4)
    a[1, 2] = np.nan
    f = tmp_path / "m.npy"
    np.save(f, a)
    x, y, z = preston.read_map(f, pitch_mm=0.5, units="mm,mm,um")
    assert len(z) == 11
    i, j = np.nonzero(~np.isnan(a))
    np.testing.assert_allclose(x, (j - 1.5) * 0.5)
    np.testing.assert_allclose(y, (1.0 - i) * 0.5)
    np.testing.assert_allclose(z, a[i, j] * 1000.0)


def test_text_columns_aperture_and_removal(tmp_path):
    f = tmp_path / "m.xyz"
    pts = [(i, j, 5.0 + 2.0 * i - 1.0 * j) for i in range(-5, 6) for j in range(-5, 6)]
    f.write_text("\n".join(f"{z} {x} {y}" for x, y, z in pts))
    x, y, z = preston.read_map(f, columns="z,x,y")
    assert len(x) == 121 and z[0] == pytest.approx(5.0 - 10.0 + 5.0)
    # Circle of radius 1 holds 5 lattice points; piston + tilt remove this plane exactly.
    x, y, z = preston.read_map(f, columns="z,x,y", aperture="circle:1", remove="piston,tilt")
    assert len(x) == 5
    np.testing.assert_allclose(z, 0.0, atol=1e-9)
