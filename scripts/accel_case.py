#!/usr/bin/env python3
"""Writes the acceleration-limit benchmark case: an error map on a 0.5 mm lattice and a serpentine
raster of dwell points over it (map.csv: x_mm,y_mm,z_nm; dwell.csv: x_mm,y_mm).

usage: accel_case.py OUT_DIR MAP_NX MAP_NY DWELL_NX DWELL_NY [DWELL_PITCH_MM]

The issue's 3,200-point case: 120 x 70 map points (8,400) and an 80 x 40 raster (3,200) at 0.7 mm.
The error is a smooth form (astigmatism and coma-like terms) plus a few Gaussian bumps, 0..~200 nm.
"""
import math
import os
import sys

out, mnx, mny, dnx, dny = sys.argv[1], *map(int, sys.argv[2:6])
pitch = float(sys.argv[6]) if len(sys.argv) > 6 else 0.7
os.makedirs(out, exist_ok=True)
mp = 0.5
wx, wy = (mnx - 1) * mp, (mny - 1) * mp
bumps = [(0.3, 0.4, 3.0, 60.0), (0.7, 0.6, 2.0, -50.0), (0.5, 0.2, 4.0, 40.0), (0.2, 0.8, 2.5, 45.0)]
with open(os.path.join(out, "map.csv"), "w") as f:
    f.write("x_mm,y_mm,z_nm\n")
    for j in range(mny):
        for i in range(mnx):
            x, y = i * mp - wx / 2, j * mp - wy / 2
            u, v = x / (wx / 2), y / (wy / 2)
            z = 40.0 * (u * u - v * v) + 25.0 * (u * u + v * v) * u + 30.0 * (u * u + v * v)
            for bx, by, s, a in bumps:
                cx, cy = (bx - 0.5) * wx, (by - 0.5) * wy
                z += a * math.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
            f.write(f"{x:.4f},{y:.4f},{z:.6f}\n")
dwx, dwy = (dnx - 1) * pitch, (dny - 1) * pitch
with open(os.path.join(out, "dwell.csv"), "w") as f:
    f.write("x_mm,y_mm\n")
    for j in range(dny):
        cols = range(dnx) if j % 2 == 0 else range(dnx - 1, -1, -1)
        for i in cols:
            f.write(f"{i * pitch - dwx / 2:.4f},{j * pitch - dwy / 2:.4f}\n")
