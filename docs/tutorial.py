"""Preston from Python, worked through: from a measured map to the machine program, the plots and
the report a metrologist hands on.

Run it from anywhere (the sample data come with the package; step 5 needs scipy, which
``pip install 'preston-dwell[scipy]'`` installs with the package)::

    python docs/tutorial.py [OUT_DIR]

It writes everything into ``OUT_DIR`` (default ``tutorial-out``). Units everywhere: lengths mm,
heights nm, times s, removal rates nm/s, feeds mm/min. The test suite runs this file
(``python/tests/test_tutorial.py``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

import preston

def main(out_dir: str = "tutorial-out") -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    # 0. The sample data, shipped in the package: a job, its map and its TIF, written into a
    #    directory (as `preston sample --out DIR` does).
    data = preston.sample_job(out / "sample", overwrite=True).parent

    # 1. The measured map: the 118 x 8 mm mirror strip, x_mm, y_mm, z_nm. Any format the CLI
    #    reads works here (Zygo .datx, 4D .h5, .npy, XYZ text), with its units, an aperture and
    #    form removal: preston.read_map(path, aperture="rect:110,7", remove="piston,tilt").
    x, y, z = preston.read_map(data / "mirror_error_118x8mm.csv")
    print(f"map: {x.size} points, PV {np.ptp(z):.1f} nm, RMS {np.std(z):.1f} nm")

    # 2. Bad input raises preston.InputError, which is a ValueError and names the keyword.
    try:
        preston.solve(map_xyz=np.zeros((4, 2)), gaussian={"sigma_mm": 2.0})
    except ValueError as e:
        print(f"as expected: {e}")

    # 3. Solve: the measured TIF, a serpentine raster at 1 mm, the machine's feed limit. The
    #    keywords are the CLI's flags (preston solve --help).
    result = preston.solve(
        map_xyz=(x, y, z),
        tif=data / "tif_fluid_jet_10mm.csv",
        raster_pitch_mm=1.0,
        v_max=3000.0,
        edge="gerchberg-papoulis",
    )
    r = result.report
    print(
        f"plan: RMS {r['rms_before_nm']:.2f} -> {r['rms_after_nm']:.2f} nm, "
        f"total dwell {r['total_dwell_s']:.0f} s, status {result.status}"
    )

    # 4. The map is a lattice: the residual as a 2-D array with its axes, for numpy/matplotlib.
    grid = result.residual_grid
    print(
        f"residual grid: {grid.values.shape[1]} x {grid.values.shape[0]} "
        f"(x {grid.x_mm[0]:.2f}..{grid.x_mm[-1]:.2f} mm, y {grid.y_mm[0]:.2f}..{grid.y_mm[-1]:.2f} mm)"
    )

    # 5. R itself, for trying another optimiser: removal = R @ dwell (a scipy.sparse matrix:
    #    pip install 'preston-dwell[scipy]').
    R = preston.influence_matrix(
        map_xyz=(x, y, z),
        tif=data / "tif_fluid_jet_10mm.csv",
        raster_pitch_mm=1.0,
        v_max=3000.0,
    )
    print(f"R: {R.shape[0]} x {R.shape[1]}, {R.nnz} non-zeros")

    # 6. The program the machine runs, as text (and as a file), then that program run on the
    #    map: the check a shop makes before polishing.
    program = preston.nc(
        np.column_stack([result.dwell_x_mm, result.dwell_y_mm]),
        result.dwell_s,
        v_max_mm_per_min=3000.0,
        out=out / "program.nc",
    )
    executed = preston.simulate_program(
        data / "mirror_error_118x8mm.csv", program, tif=data / "tif_fluid_jet_10mm.csv"
    )
    check = executed["check"]
    print(
        f"program: {len(program.splitlines())} lines; executed RMS "
        f"{executed['report']['rms_after_nm']:.2f} nm, worst stretch "
        f"{100 * check['max_relative_error']:.3f}% off its dwell"
    )

    # 7. The files: CSVs, report.json, the plots and report.html (one page to hand on).
    notes = result.write(out, plots=True, report=True)
    for note in notes:
        print(f"note: {note}")
    print(f"wrote {out / 'report.html'}")
    return {
        "result": result,
        "grid": grid,
        "R": R,
        "program": program,
        "executed": executed,
        "out": out,
    }


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else os.environ.get("PRESTON_TUTORIAL_OUT", "tutorial-out"))
