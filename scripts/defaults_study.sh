#!/usr/bin/env bash
# The executed residual of the sample job's settings against the alternatives (edge model, feed
# floor, raster pitch) on the shipped map and on two other maps of data/: every row is
# the plan executed at the job's acceleration limit with look-ahead (report.json rms_after_nm,
# the program as the machine runs it). Prints a Markdown table; docs/part_quality.md holds the
# figures. Usage: scripts/defaults_study.sh [DATA_DIR, default data] > table.md
set -euo pipefail
cd "$(dirname "$0")/.."
SHARED="${1:-data}"
BIN="${PRESTON_BIN:-target/release/preston}"
OUT="${TMPDIR:-/tmp}/preston-defaults-study"
mkdir -p "$OUT"
row() { # name, then solve flags
    local name="$1"; shift
    local dir="$OUT/$(echo "$name" | tr -c 'A-Za-z0-9' _)"
    local t0=$(date +%s.%N)
    if "$BIN" solve --job data/job.toml "$@" --out "$dir" --quiet >"$dir.log" 2>&1 || [ $? -eq 3 ]; then
        local t1=$(date +%s.%N)
        python3 - "$dir" "$name" "$t0" "$t1" "$*" <<'PY'
import json, sys, csv
d, name, t0, t1, flags = sys.argv[1:]
r = json.load(open(f"{d}/report.json"))
dw = [float(row["dwell_s"]) for row in csv.DictReader(open(f"{d}/dwell.csv"))]
e = r.get("executed") or {}
planned = (r.get("model") or {}).get("rms_nm", r["rms_after_nm"])
print(f"| {name} | `{flags}` | {r['rms_after_nm']:.3f} / {r['pv_after_nm']:.2f} | {planned:.3f} | "
      f"{r['total_dwell_s']:,.0f} | {max(dw):.1f} | {r['max_accel_mm_per_s2']:.0f} | {float(t1)-float(t0):.1f} |")
PY
    else
        echo "| $name | \`$*\` | failed (see $dir.log) | | | | | |"
    fi
}
echo "| case | flags over \`--job data/job.toml\` | executed RMS / PV (nm) | model RMS (nm) | dwell (s) | largest dwell (s) | max accel between programmed feeds (mm/s^2) | wall (s) |"
echo "| --- | --- | --- | --- | --- | --- | --- | --- |"
# The shipped map and TIF: the sample job as shipped, then one setting changed at a time.
row "sample: as shipped"
for e in zero-band gaussian polynomial gerchberg-papoulis; do row "sample: edge $e" --edge "$e"; done
row "sample: no feed floor" --v-min 0
for p in 1.0 0.75 0.5; do row "sample: pitch $p mm" --raster-pitch-mm "$p"; done
# Another mirror, the same measured TIF.
M2="$SHARED/mirror_sim_210x30mm.csv"
for p in 1.0 0.75; do row "210x30 mirror: pitch $p mm" --map "$M2" --raster-pitch-mm "$p"; done
row "210x30 mirror: edge gerchberg-papoulis, 1 mm" --map "$M2" --raster-pitch-mm 1.0 --edge gerchberg-papoulis
row "210x30 mirror: no feed floor, 1 mm" --map "$M2" --raster-pitch-mm 1.0 --v-min 0
# An ion-beam map with a Gaussian TIF (sigma 1.5 mm, 6 nm/s).
M3="$SHARED/ibf_sim_70x30mm_0.1mm.csv"
G="--gaussian-sigma-mm 1.5 --gaussian-peak-nm-per-s 6"
for p in 1.0 0.5; do row "70x30 IBF map, Gaussian TIF: pitch $p mm" --map "$M3" $G --raster-pitch-mm "$p"; done
row "70x30 IBF map, Gaussian TIF: edge gerchberg-papoulis, 1 mm" --map "$M3" $G --raster-pitch-mm 1.0 --edge gerchberg-papoulis
