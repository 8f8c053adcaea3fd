#!/usr/bin/env python3
"""A round part's error map and job, for the round-part operator study (docs/off_lattice.md,
"Round parts: spirals and random paths").

Writes DIR/round_<D>mm.csv (`x_mm,y_mm,z_nm`: the map points inside the part's radius on a
lattice of --pitch-mm through the centre) and DIR/round_<D>mm.toml (the map, a Gaussian TIF of
sigma 3 mm and peak 10 nm/s cut at 9 mm, v_max 3000 mm/min, v_min 1 mm/min, a_max 1000 mm/s^2).
The height is 120 nm PV of low-order form (defocus, astigmatism, coma, trefoil), an 11 x 13 mm
ripple of 3 nm amplitude and 1 nm RMS of Gaussian noise, from a fixed seed: the same map for the
same arguments. Standard library only.

Usage: scripts/round_part.py [--diameter-mm 100] [--pitch-mm 0.5] [--seed 57] [DIR]
The paths (a spiral to the radius plus the TIF's 6 mm, a random path over the same square):
  preston path spiral --radius-mm 56 --pitch-mm 1 --out DIR/spiral.csv
  preston path random --x-mm=-56,56 --y-mm=-56,56 --pitch-mm 1 --out DIR/random.csv
"""
import argparse
import math
import os
import random


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dir", nargs="?", default=".")
    ap.add_argument("--diameter-mm", type=float, default=100.0)
    ap.add_argument("--pitch-mm", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=57)
    a = ap.parse_args()
    os.makedirs(a.dir, exist_ok=True)
    radius = a.diameter_mm / 2
    rng = random.Random(a.seed)
    n = int(math.floor(radius / a.pitch_mm))
    pts = []
    for j in range(-n, n + 1):
        for i in range(-n, n + 1):
            x, y = i * a.pitch_mm, j * a.pitch_mm
            if x * x + y * y <= radius * radius:
                pts.append((x, y))

    def form(x, y):
        u, v = x / radius, y / radius
        r2 = u * u + v * v
        return (
            (2 * r2 - 1)  # defocus
            + 0.6 * (u * u - v * v)  # astigmatism
            + 0.4 * (3 * r2 - 2) * v  # coma
            + 0.3 * (u ** 3 - 3 * u * v * v)  # trefoil
        )

    vals = [form(x, y) for x, y in pts]
    lo, hi = min(vals), max(vals)
    scale = 120.0 / (hi - lo)
    name = f"round_{a.diameter_mm:g}mm"
    with open(os.path.join(a.dir, name + ".csv"), "w") as f:
        f.write("x_mm,y_mm,z_nm\n")
        for (x, y), v in zip(pts, vals):
            ripple = 3.0 * math.sin(2 * math.pi * x / 11.0) * math.sin(2 * math.pi * y / 13.0)
            z = scale * (v - lo) + ripple + rng.gauss(0.0, 1.0)
            f.write(f"{x:.4f},{y:.4f},{z:.4f}\n")
    with open(os.path.join(a.dir, name + ".toml"), "w") as f:
        f.write(
            f"""# A {a.diameter_mm:g} mm round part (scripts/round_part.py, seed {a.seed}): {len(pts)} map points
# at {a.pitch_mm:g} mm. Give the path on the command line: --raster-pitch-mm 1, or --dwell with a
# spiral or random path (the script's usage).
[map]
file = "{name}.csv"

[tif]
gaussian = {{ sigma_mm = 3.0, peak_rate_nm_per_s = 10.0, truncation_radius_mm = 9.0 }}

[machine]
v_max_mm_per_min = 3000.0
v_min_mm_per_min = 1.0
a_max_mm_per_s2 = 1000.0
"""
        )
    print(f"{len(pts)} map points -> {os.path.join(a.dir, name + '.csv')}")


if __name__ == "__main__":
    main()
