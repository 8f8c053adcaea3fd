"""Tool paths with every option of ``preston path``: equal to the CLI's CSV and summary on the same
inputs, the geometry they promise (arc turns, chord heights, aperture, projection), and their
error paths."""

import json
import math
import subprocess

import numpy as np
import pytest

import preston

from conftest import DATA

FREEFORM = DATA / "design_freeform.json"
#: An oblate ellipsoid (R = 100 mm, k = 0.6), the CLI tests' chord-height surface.
ELLIPSOID = {"type": "conic", "curvature_per_mm": 0.01, "conic": 0.6}
#: Tangents are unit vectors to rounding.
UNIT_TOL = 1e-12
#: Geometric tolerance of the closed-form checks, mm.
GEOM_TOL_MM = 1e-9


def cli(preston_bin, *args):
    p = subprocess.run([str(preston_bin), *map(str, args)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


def cli_fails(preston_bin, *args):
    p = subprocess.run([str(preston_bin), *map(str, args)], capture_output=True, text=True)
    assert p.returncode != 0
    return p.stderr


def read_path_csv(path):
    with open(path) as f:
        header = f.readline().strip().split(",")
    assert header == list(preston.ToolPath.__slots__[:7])
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)


def same_path(tp, csv_path, printed, extra_keys=()):
    """The ToolPath's columns equal the CLI's CSV (the CSV holds shortest round-trip decimals, so
    the values are equal exactly) and its summary has the CLI's keys and values."""
    assert all(getattr(tp, c).dtype == np.float64 for c in preston.ToolPath.__slots__[:7])
    np.testing.assert_array_equal(tp.columns, read_path_csv(csv_path))
    for k, v in printed.items():
        assert tp.summary[k] == v, k
    assert len(tp) == printed["points"]


@pytest.fixture
def aperture_csv(tmp_path):
    """A hexagon of circumradius 12 mm about (1, -2) mm, as an (N, 2) array and a CSV file."""
    t = np.radians(np.arange(6) * 60.0 + 15.0)
    poly = np.column_stack([1.0 + 12.0 * np.cos(t), -2.0 + 12.0 * np.sin(t)])
    f = tmp_path / "aperture.csv"
    np.savetxt(f, poly, delimiter=",", header="x_mm,y_mm", comments="")
    return poly, f


def test_raster_with_every_option_equals_cli(preston_bin, tmp_path, aperture_csv):
    poly, poly_csv = aperture_csv
    out = tmp_path / "r.csv"
    cases = [
        (["--along", "y"], dict(along="y")),
        (["--step-mm", 0.4, "--margin-mm", 1.5], dict(step_mm=0.4, margin_mm=1.5)),
        (["--arc-radius-mm", 0.75, "--arc-tolerance-um", 0.5, "--step-mm", 0.3],
         dict(arc_radius_mm=0.75, arc_tolerance_um=0.5, step_mm=0.3)),
        (["--aperture", poly_csv, "--margin-mm", 1.0], dict(aperture_xy=poly, margin_mm=1.0)),
        (["--surface", FREEFORM, "--arc-radius-mm", 1.0], dict(surface=FREEFORM, arc_radius_mm=1.0)),
    ]
    for args, kw in cases:
        printed = cli(preston_bin, "path", "raster", "--x-mm", "-10,12", "--y-mm", "-15,9",
                      "--pitch-mm", 2.0, *args, "--out", out)
        tp = preston.path_raster((-10, 12), (-15, 9), 2.0, **kw)
        same_path(tp, out, printed)


def test_intersection_iterations_equal_cli(preston_bin, tmp_path, aperture_csv):
    poly, poly_csv = aperture_csv
    out = tmp_path / "i.csv"
    for k in range(5):
        printed = cli(preston_bin, "path", "intersection", "--x-mm", "-12,10", "--y-mm", "-14,10",
                      "--pitch-mm", 1.5, "--iteration", k, "--arc-radius-mm", 0.5, "--aperture",
                      poly_csv, "--margin-mm", 0.5, "--surface", FREEFORM, "--out", out)
        tp = preston.path_intersection((-12, 10), (-14, 10), 1.5, k, arc_radius_mm=0.5,
                                       aperture_xy=poly, margin_mm=0.5, surface=FREEFORM)
        same_path(tp, out, printed)
        # The pattern: x, y, x + P/2, y + P/2, repeating.
        assert tp.summary["along"] == ("x" if k % 2 == 0 else "y")
        assert tp.summary["shift_mm"] == (0.75 if (k // 2) % 2 == 1 else 0.0)


def test_intersection_lines_and_shift():
    """Iteration 2 is iteration 0 moved across by P/2: its lines lie at y0 + P/2 + k P."""
    p0 = preston.path_intersection((0, 10), (0, 8), 2.0, 0)
    p2 = preston.path_intersection((0, 10), (0, 8), 2.0, 2)
    assert np.all(np.isin(np.round(p0.y_mm, 9), np.arange(-1, 6) * 2.0))
    assert np.all(np.isin(np.round(p2.y_mm, 9), np.arange(-1, 6) * 2.0 - 1.0))
    p1 = preston.path_intersection((0, 10), (0, 8), 2.0, 1)
    assert np.all(np.isin(np.round(p1.x_mm, 9), np.arange(-1, 7) * 2.0))


def test_arc_turns_are_tangent_continuous():
    """With arcs of radius r the turn between two points is at most the chord angle of the arc
    sampling; sharp corners turn by 90 degrees."""
    sharp = preston.path_raster((0, 20), (0, 10), 2.0, step_mm=0.25)
    arcs = preston.path_raster((0, 20), (0, 10), 2.0, step_mm=0.25, arc_radius_mm=1.0,
                               arc_tolerance_um=1.0)

    def max_turn(tp):
        d = np.diff(tp.xy, axis=0)
        d = d / np.linalg.norm(d, axis=1)[:, None]
        c = np.clip(np.sum(d[1:] * d[:-1], axis=1), -1.0, 1.0)
        return np.degrees(np.max(np.arccos(c)))

    assert max_turn(sharp) == pytest.approx(90.0, abs=1e-9)
    # A chord of an r = 1 mm arc within 1 um sags by at most 1 um: its angle phi satisfies
    # 1 - cos(phi / 2) <= 1e-3, so the turn between chords is at most phi.
    phi = math.degrees(2.0 * math.acos(1.0 - 1e-3))
    assert max_turn(arcs) <= phi + 1e-9
    # The arcs lie outside the line ends by r.
    assert arcs.x_mm.max() == pytest.approx(21.0, abs=GEOM_TOL_MM)
    assert arcs.x_mm.min() == pytest.approx(-1.0, abs=GEOM_TOL_MM)


def test_aperture_clipping_keeps_points_within_the_margin(aperture_csv):
    poly, _ = aperture_csv
    full = preston.path_raster((-15, 15), (-15, 15), 1.0)
    clipped = preston.path_raster((-15, 15), (-15, 15), 1.0, aperture_xy=poly)
    assert 0 < len(clipped) < len(full)
    # Every kept point is inside the hexagon: closer to its centre than the circumradius.
    r = np.hypot(clipped.x_mm - 1.0, clipped.y_mm + 2.0)
    assert r.max() <= 12.0 + GEOM_TOL_MM
    # The inscribed circle (radius 12 cos 30 deg) is kept whole.
    r_full = np.hypot(full.x_mm - 1.0, full.y_mm + 2.0)
    assert np.sum(r_full < 12.0 * math.cos(math.radians(30))) <= len(clipped)


def test_chord_height_equals_cli_and_keeps_the_window(preston_bin, tmp_path):
    surf = tmp_path / "ell.json"
    surf.write_text(json.dumps(ELLIPSOID))
    out = tmp_path / "c.csv"
    printed = cli(preston_bin, "path", "chord-height", "--surface", surf, "--line-x-mm", 10,
                  "--y-mm", "-30,30", "--tool-radius-mm", 10, "--eps-um", "3.0,3.2",
                  "--grow-mm", 0.1, "--shrink-mm", 0.02, "--out", out)
    tp = preston.path_chord_height(ELLIPSOID, 10.0, (-30, 30), 10.0, (3.0, 3.2),
                                   grow_mm=0.1, shrink_mm=0.02)
    same_path(tp, out, printed)
    # Every chord but the last (cut at the line's end) keeps its height in the window.
    h = tp.summary["chord_heights_um"]
    assert len(h) == len(tp) - 1 == len(tp.summary["steps_mm"])
    assert np.all((h[:-1] >= 3.0) & (h[:-1] <= 3.2))
    # Steps are 3-D chord lengths between consecutive points on the surface.
    chords = np.hypot(np.diff(tp.y_mm), np.diff(tp.z_mm))
    np.testing.assert_allclose(tp.summary["steps_mm"], chords, rtol=1e-12, atol=0)
    assert tp.y_mm[0] == -30.0 and tp.y_mm[-1] == 30.0
    # The points lie on the line and on the ellipsoid.
    assert np.all(tp.x_mm == 10.0)
    rho2 = tp.x_mm**2 + tp.y_mm**2
    sag = 0.01 * rho2 / (1.0 + np.sqrt(1.0 - 1.6 * 0.01**2 * rho2))
    np.testing.assert_allclose(tp.z_mm, sag, rtol=0, atol=1e-12)


def test_projection_equals_cli_for_the_other_kinds(preston_bin, tmp_path):
    """spiral / random / edge-offset with --surface: their (x, y) through path_project."""
    out = tmp_path / "p.csv"
    printed = cli(preston_bin, "path", "spiral", "--radius-mm", 15, "--pitch-mm", 1.5,
                  "--step-mm", 0.7, "--centre-mm", "1,-2", "--surface", FREEFORM, "--out", out)
    x, y = preston.path_spiral(15, 1.5, step_mm=0.7, centre_mm=(1, -2))
    tp = preston.path_project((x, y), FREEFORM)
    np.testing.assert_array_equal(tp.columns, read_path_csv(out))
    assert sum(tp.ds_mm) == pytest.approx(printed["length_mm"], rel=1e-12)

    printed = cli(preston_bin, "path", "random", "--x-mm", "-8,8", "--y-mm", "-6,6",
                  "--pitch-mm", 1.0, "--seed", 3, "--jitter", 0.2, "--surface", FREEFORM, "--out", out)
    x, y, _ = preston.path_random((-8, 8), (-6, 6), 1.0, seed=3, jitter=0.2)
    tp = preston.path_project(np.column_stack([x, y]), json.loads(FREEFORM.read_text()))
    np.testing.assert_array_equal(tp.columns, read_path_csv(out))

    printed = cli(preston_bin, "path", "edge-offset", "--edge-radius-mm", 40, "--bonnet-radius-mm",
                  20, "--spot-max-mm", 6, "--spot-min-mm", 1.5, "--ratio", 0.8, "--residual-um", 1,
                  "--surface", FREEFORM, "--out", out)
    x, y, _ = preston.path_edge_offset(edge_radius_mm=40, bonnet_radius_mm=20, spot_max_mm=6,
                                       spot_min_mm=1.5, ratio=0.8, residual_um=1)
    tp = preston.path_project((x, y), FREEFORM)
    np.testing.assert_array_equal(tp.columns, read_path_csv(out))


def test_projection_geometry():
    """Flat: z = 0, tangents in the plane, ds as DwellPath's contract. On a sphere: unit
    tangents, and ds along the surface no shorter than in plan."""
    x, y = preston.path_spiral(10, 1.0)
    flat = preston.path_project((x, y))
    assert np.all(flat.z_mm == 0.0) and np.all(flat.tz == 0.0)
    seg = np.hypot(np.diff(x), np.diff(y))
    want = np.concatenate([[seg[0]], 0.5 * (seg[1:] + seg[:-1]), [seg[-1]]])
    np.testing.assert_allclose(flat.ds_mm, want, rtol=1e-15, atol=0)
    sphere = preston.path_project((x, y), {"type": "conic", "curvature_per_mm": 0.02})
    norm = np.sqrt(sphere.tx**2 + sphere.ty**2 + sphere.tz**2)
    np.testing.assert_allclose(norm, 1.0, rtol=0, atol=UNIT_TOL)
    assert np.all(sphere.ds_mm >= flat.ds_mm - 1e-12)
    assert sphere.xy.shape == (len(x), 2)


def test_path_errors_carry_prestons_message(preston_bin, tmp_path):
    bad = [
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, along="z"), "along"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, margin_mm=-1), "margin_mm must be non-negative"),
        (lambda: preston.path_raster((0, 10), (0, 10), 0.0), "pitch"),
        (lambda: preston.path_raster((0, 10), (0, 10), -1.0), "pitch"),
        (lambda: preston.path_raster((0, 1e6), (0, 1e6), 1e-4), "pitch_mm"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, step_mm=0.0), "step"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, arc_radius_mm=0.6), "arc"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, arc_radius_mm=-0.1), "arc radius"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, arc_radius_mm=0.5, arc_tolerance_um=0),
         "arc tolerance"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, aperture_xy=[[0, 0], [1, 1]]),
         "three vertices"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, aperture_xy=np.zeros((4, 3))), "aperture_xy"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, aperture_xy=[[50, 50], [51, 50], [51, 51]]),
         "no path point lies in the aperture"),
        (lambda: preston.path_raster((0, 10), (0,), 1.0), "y_range_mm"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, surface={"type": "torus"}), "surface"),
        (lambda: preston.path_raster((0, 10), (0, 10), 1.0, surface=tmp_path / "missing.json"),
         "missing.json"),
        (lambda: preston.path_raster((0, 30), (0, 30), 1.0, surface={"type": "conic", "curvature_per_mm": 0.1}),
         "surface"),
        (lambda: preston.path_intersection((0, 10), (0, 10), 1.0, -1), "iteration"),
        (lambda: preston.path_chord_height(ELLIPSOID, 10, (-30, 30), 10, (3.2, 3.0)), "eps"),
        (lambda: preston.path_chord_height(ELLIPSOID, 10, (5, 5), 10, (3.0, 3.2)), "chord-height line"),
        (lambda: preston.path_chord_height(ELLIPSOID, 10, (-30, 30), -1, (3.0, 3.2)), "tool_radius"),
        (lambda: preston.path_chord_height({"type": "conic", "curvature_per_mm": "x"}, 10, (-30, 30), 10,
                                           (3.0, 3.2)), "surface"),
        (lambda: preston.path_project(np.zeros((3, 3))), "points_xy"),
        (lambda: preston.path_project([[0.0, np.nan], [1.0, 1.0]]), "points_xy"),
        (lambda: preston.path_project([[50.0, 0.0], [0.0, 0.0]], {"type": "conic", "curvature_per_mm": 0.1}),
         "surface"),
    ]
    for call, needle in bad:
        with pytest.raises(preston.InputError) as e:
            call()
        assert needle in str(e.value), (needle, str(e.value))
    # The same bad input through the CLI fails too, with the same reason (the engine's message).
    err = cli_fails(preston_bin, "path", "raster", "--x-mm", "0,10", "--y-mm", "0,10", "--pitch-mm", 1,
                    "--arc-radius-mm", 0.6, "--out", tmp_path / "x.csv")
    with pytest.raises(preston.InputError) as e:
        preston.path_raster((0, 10), (0, 10), 1.0, arc_radius_mm=0.6)
    engine_message = str(e.value).split(": ", 1)[1]
    assert engine_message in err, (engine_message, err)
