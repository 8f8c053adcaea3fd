"""The figures of ``preston solve --plots`` and the PSDs of ``psd.csv`` from a Python solve: the
same files as the CLI's on the same job, PNGs of the layout's pixel size, and the error paths."""

import json
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

import preston

from conftest import write_small_job

FIGURES = ("error_before.png", "removal.png", "residual.png", "dwell.png", "feed.png", "path.png",
           "tif.png", "psd.png", "psd.csv", "psd_2d.png", "psd_2d.csv", "psd_azimuthal.png",
           "psd_azimuthal.csv")
# The layout of io/src/plots.rs, pixels: map canvas width, title, y labels, x labels, right
# margin, colour-bar strip, tallest and shortest data area; the PSD plot's fixed size.
MAP_WIDTH, TITLE, Y_LABELS, X_LABELS, RIGHT, BAR, MAX_H, MIN_H = 1000, 44, 72, 48, 36, 76, 720, 40
PSD_SIZE = (900, 700)


def png_size(path: Path):
    """Width and height from the PNG's IHDR chunk, after checking the signature and the chunk's
    CRC; the image data must inflate to height rows of 1 + 3 width bytes (RGB, 8 bit)."""
    b = path.read_bytes()
    assert b[:8] == b"\x89PNG\r\n\x1a\n", path
    length, kind = struct.unpack(">I4s", b[8:16])
    assert kind == b"IHDR" and length == 13
    w, h, depth, colour = struct.unpack(">IIBB", b[16:26])
    assert (struct.unpack(">I", b[29:33])[0]) == zlib.crc32(b[12:29])
    assert depth == 8 and colour == 2
    data, i = b"", 33
    while i < len(b):
        n, k = struct.unpack(">I4s", b[i : i + 8])
        if k == b"IDAT":
            data += b[i + 8 : i + 8 + n]
        i += 12 + n
    assert len(zlib.decompress(data)) == h * (1 + 3 * w)
    return w, h


def map_canvas(width_mm: float, height_mm: float):
    """The canvas of a map plot: equal mm per pixel, the long side across (MapLayout)."""
    across, down = max(width_mm, height_mm), min(width_mm, height_mm)
    w = MAP_WIDTH - Y_LABELS - RIGHT
    h = w * down / across
    if h > MAX_H:
        h, w = MAX_H, MAX_H * across / down
    if h < MIN_H:
        h, w = MIN_H, MIN_H * across / down
    w, h = max(round(w), 1), max(round(h), 1)
    return max(Y_LABELS + w + RIGHT, MAP_WIDTH), TITLE + h + X_LABELS + BAR


def to_toml(job: dict) -> str:
    """A job dict of tables of scalars (and one nested table level) as TOML."""
    lines = []

    def scalar(v):
        return json.dumps(v) if isinstance(v, str) else repr(v).lower() if isinstance(v, bool) else repr(v)

    def table(name, d):
        lines.append(f"[{name}]")
        for k, v in d.items():
            if not isinstance(v, dict):
                lines.append(f"{k} = {scalar(v)}")
        for k, v in d.items():
            if isinstance(v, dict):
                table(f"{name}.{k}", v)

    for name, d in job.items():
        table(name, d)
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module", params=["x", "y"])
def solved(request, preston_bin, tmp_path_factory):
    """The small job (raster along x, then along y) solved by the CLI with --plots and in Python."""
    d = tmp_path_factory.mktemp(f"plots_{request.param}")
    job = write_small_job(d)
    job["dwell"]["raster_along"] = request.param
    (d / "job.toml").write_text(to_toml(job))
    cli_out = d / "cli"
    subprocess.run([str(preston_bin), "solve", "--job", str(d / "job.toml"), "--out", str(cli_out),
                    "--plots"], check=True, capture_output=True)
    return preston.solve(d / "job.toml"), cli_out, request.param


def test_write_plots_equals_the_cli_figures(solved, tmp_path):
    r, cli_out, _ = solved
    files, notes = r.write_plots(tmp_path / "figs")
    assert notes == []
    assert sorted(f.name for f in files) == sorted(FIGURES)
    assert {p.name for p in (tmp_path / "figs").iterdir()} == set(FIGURES)
    for f in files:
        assert f.stat().st_size > 0
        # The same engine on the same inputs: the same bytes as `preston solve --plots`.
        assert f.read_bytes() == (cli_out / f.name).read_bytes(), f.name


def test_svg_figures_are_the_png_figures_as_svg(solved, tmp_path):
    """``plot_format="svg"``: the same figures as SVG documents of the PNGs' sizes, the CSVs
    the same bytes, and ``write(..., plots=True, plot_format="svg")`` the same files."""
    r, cli_out, _ = solved
    files, notes = r.write_plots(tmp_path / "svg", plot_format="svg")
    assert notes == []
    want = sorted(f.replace(".png", ".svg") for f in FIGURES)
    assert sorted(f.name for f in files) == want
    for f in files:
        if f.suffix == ".svg":
            text = f.read_text()
            w, h = png_size(cli_out / (f.stem + ".png"))
            assert text.startswith(f'<svg width="{w}" height="{h}"'), f.name
            assert text.rstrip().endswith("</svg>"), f.name
        else:
            assert f.read_bytes() == (cli_out / f.name).read_bytes(), f.name
    r.write(tmp_path / "all", plots=True, plot_format="svg")
    for f in files:
        assert (tmp_path / "all" / f.name).read_bytes() == f.read_bytes(), f.name
    with pytest.raises(ValueError, match="plot_format"):
        r.write_plots(tmp_path / "bad", plot_format="jpeg")


def test_png_pixel_sizes(solved, tmp_path):
    r, _, _ = solved
    files, _ = r.write_plots(tmp_path)
    size = {f.name: png_size(f) for f in files if f.suffix == ".png"}
    # Map cells are the lattice pitch (0.8 mm) wide, so the data extent is the points' extent
    # plus one pitch: 24.8 x 16.8 mm, drawn 892 px wide.
    w_mm = np.ptp(r.map_x_mm) + 0.8
    h_mm = np.ptp(r.map_y_mm) + 0.8
    for name in ("error_before.png", "removal.png", "residual.png"):
        assert size[name] == map_canvas(w_mm, h_mm) == (1000, 44 + 604 + 48 + 76), name
    assert size["dwell.png"] == size["feed.png"] and size["dwell.png"][0] == MAP_WIDTH
    dw, dh = np.ptp(r.dwell_x_mm), np.ptp(r.dwell_y_mm)
    # The path plot pads the extent by 2% of its larger side and has no colour bar.
    pad = 0.02 * max(dw, dh)
    cw, ch = map_canvas(dw + 2 * pad, dh + 2 * pad)
    assert size["path.png"] == (cw, ch - BAR)
    # The TIF plot is square (2 r by 2 r).
    assert size["tif.png"] == map_canvas(1.0, 1.0) == (MAP_WIDTH, TITLE + MAX_H + X_LABELS + BAR)
    assert size["psd.png"] == PSD_SIZE


def test_psd_arrays_equal_psd_csv(solved):
    r, cli_out, along = solved
    psd = r.psd()
    assert psd["along"] == along
    table = np.loadtxt(cli_out / "psd.csv", delimiter=",", skiprows=1)
    assert (cli_out / "psd.csv").read_text().splitlines()[0] == (
        "frequency_per_mm,error_psd_nm2_mm,residual_psd_nm2_mm"
    )
    for k, col in (("frequency_per_mm", 0), ("error_psd_nm2_mm", 1), ("residual_psd_nm2_mm", 2)):
        assert psd[k].dtype == np.float64
        np.testing.assert_array_equal(psd[k], table[:, col])
    # Frequencies k / (L p), k = 0..L/2, on the map's 0.8 mm lattice.
    L, p = psd["segment_points"], psd["pitch_mm"]
    assert p == pytest.approx(0.8, rel=1e-12)
    np.testing.assert_allclose(psd["frequency_per_mm"], np.arange(L // 2 + 1) / (L * p), rtol=1e-12)
    assert psd["segments"] >= 1


def test_psd_peaks_at_the_error_frequencies(small_job):
    """A pure cosine of 6 cycles along x over 24 mm puts its power at 0.25 /mm, along x only."""
    r = preston.solve(small_job)
    x = r.psd("x")
    y = r.psd("y")
    assert x["along"] == "x" and y["along"] == "y"
    # The error is 90 + 30 cos(2 pi x / 24) + 20 sin(2 pi y / 16): along x the peak is at 1/24 /mm.
    f = x["frequency_per_mm"]
    k = int(np.argmax(x["error_psd_nm2_mm"][1:])) + 1
    assert abs(f[k] - 1.0 / 24.0) <= f[1]
    ky = int(np.argmax(y["error_psd_nm2_mm"][1:])) + 1
    assert abs(y["frequency_per_mm"][ky] - 1.0 / 16.0) <= y["frequency_per_mm"][1]


def test_write_with_plots_writes_everything_together(solved, tmp_path):
    r, cli_out, _ = solved
    notes = r.write(tmp_path / "all", plots=True)
    assert notes == []
    names = {p.name for p in (tmp_path / "all").iterdir()}
    assert names == set(FIGURES) | {"dwell.csv", "residual.csv", "report.json"}
    for f in ("dwell.csv", "residual.csv", "psd.csv", "dwell.png"):
        assert (tmp_path / "all" / f).read_bytes() == (cli_out / f).read_bytes(), f
    # Without plots: the three files only.
    assert r.write(tmp_path / "plain") == []
    assert {p.name for p in (tmp_path / "plain").iterdir()} == {"dwell.csv", "residual.csv", "report.json"}


def test_off_lattice_map_has_no_psd(tmp_path):
    """Scattered map points: the maps and the path are drawn, the PSD is a note (as the CLI)."""
    rng = np.random.default_rng(5)
    x = rng.uniform(0, 20, 400)
    y = rng.uniform(0, 12, 400)
    z = 50 + 10 * np.cos(x / 3.0)
    r = preston.solve(map_xyz=np.column_stack([x, y, z]),
                      gaussian={"sigma_mm": 1.5, "peak_rate_nm_per_s": 20.0, "truncation_radius_mm": 4.5},
                      raster_pitch_mm=1.0, v_max=3000.0, solver="qp")
    files, notes = r.write_plots(tmp_path / "f")
    assert len(notes) == 1 and notes[0].startswith("no psd.png / psd.csv")
    assert not (tmp_path / "f" / "psd.csv").exists()
    assert {f.name for f in files} == {f for f in FIGURES if not f.startswith("psd")}
    assert all(f.stat().st_size > 0 for f in files)
    with pytest.raises(preston.InputError) as e:
        r.psd()
    assert "psd" in str(e.value)


def test_plot_errors(small_job, tmp_path):
    r = preston.solve(small_job)
    with pytest.raises(preston.InputError) as e:
        r.psd("z")
    assert "along" in str(e.value)
    with pytest.raises(preston.InputError) as e:
        r.write_plots(tmp_path, along="diagonal")
    assert "along" in str(e.value)
    # An output directory that is a file: nothing is written, Preston's message names it.
    f = tmp_path / "not_a_dir"
    f.write_text("x")
    with pytest.raises(preston.InputError) as e:
        r.write_plots(f)
    assert "not_a_dir" in str(e.value)
    # A figure whose destination is a directory: the commit refuses before renaming anything.
    out = tmp_path / "blocked"
    (out / "psd.png").mkdir(parents=True)
    with pytest.raises(preston.InputError) as e:
        r.write(out, plots=True)
    assert "psd.png" in str(e.value)
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == ["psd.png"]
