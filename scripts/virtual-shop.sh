#!/usr/bin/env bash
# Rehearses the measure-calibrate-plan-polish loop on the sample job in a virtual shop whose tool
# is not the spot test: runs RUNS runs, calibrating the tool from each run's measured removal.
#
#   scripts/virtual-shop.sh OUT [RUNS] [extra `preston shop` tool flags...]
#
# Default tool: rate 1.08, width 1.05, offset (0.15, -0.12) mm, linear skew 0.1, drift 3% per
# run; the rate wanders by -1% per run. Another shop: RATE= (the first run's rate factor),
# TOOL_FLAGS= (the `preston shop --tool-*` flags in place of the default tool's) and SEED= (the
# first measurement's noise). Another part: SURFACE= (its true surface, x_mm,y_mm,z_nm) and JOB=
# (the job each run plans with, its map replaced by the run's measurement). Prints one line per run: measured RMS before, the plan's expected
# RMS and range, the measured RMS after, the dwell.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?output folder}
RUNS=${2:-3}
shift $(( $# > 1 ? 2 : 1 ))
P=${PRESTON:-target/release/preston}
TIF=data/tif_fluid_jet_10mm.csv
JOB=${JOB:-data/job.toml}
RATE=${RATE:-1.08}
TOOL=(${TOOL_FLAGS:---tool-width-factor 1.05 --tool-offset-mm 0.15,-0.12 --tool-skew 0.1 --tool-skew-angle-deg 30 --tool-drift-per-run 0.03} "$@")
mkdir -p "$OUT"
"$P" shop --quiet --surface "${SURFACE:-data/mirror_error_118x8mm.csv}" --tif "$TIF" --seed ${SEED:-100} --out "$OUT/v0"
surface="$OUT/v0/surface_after.csv"
measured="$OUT/v0/measured.csv"
calibration=()
tif="$TIF"
printf 'run,measured_before_nm,expected_rms_nm,expected_low_nm,expected_high_nm,measured_after_nm,true_after_nm,dwell_s\n'
for run in $(seq 1 "$RUNS"); do
    d="$OUT/run$run"
    "$P" solve --quiet --job "$JOB" --map "$measured" --tif "$tif" "${calibration[@]}" --out "$d" || true
    "$P" nc --quiet --dwell "$d/dwell.csv" --job "$JOB" --out "$d/prog.nc"
    "$P" shop --quiet --surface "$surface" --program "$d/prog.nc" --tif "$TIF" --a-max-mm-per-s2 1000 \
        --tool-rate-factor "$RATE" "${TOOL[@]}" --seed $((100 + run)) --out "$d/shop"
    "$P" calibrate --quiet --before "$measured" --after "$d/shop/measured.csv" --program "$d/prog.nc" \
        --tif "$TIF" --a-max-mm-per-s2 1000 --out "$d/calibration"
    python3 - "$d" "$run" <<'PY'
import json, sys
d, run = sys.argv[1], sys.argv[2]
r = json.load(open(f"{d}/report.json"))
s = json.load(open(f"{d}/shop/shop.json"))
lo, hi = (r.get("expected_rms_range_nm") or [float("nan")] * 2)
print(f"{run},{r['rms_before_nm']:.3f},{r.get('expected_rms_nm', float('nan')):.3f},{lo:.3f},{hi:.3f},"
      f"{s['measured_rms_nm']:.3f},{s['true_rms_after_nm']:.3f},{r['total_dwell_s']:.0f}")
PY
    surface="$d/shop/surface_after.csv"
    measured="$d/shop/measured.csv"
    tif="$d/calibration/tif.csv"
    calibration=(--calibration "$d/calibration/calibration.json")
    RATE=$(python3 -c "print($RATE - 0.01)")
done
