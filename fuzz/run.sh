#!/usr/bin/env bash
# Runs each Preston fuzz target for SECONDS (default 60) with cargo-fuzz on the stable toolchain.
#
#   fuzz/run.sh [SECONDS] [TARGET...]      # targets: csv_table job tif_csv map_xyz map_npy
#                                            map_zygo_dat map_zygo_datx map_four_d_h5 (default: all)
#
# cargo-fuzz passes nightly-only flags (-Z...) to rustc; RUSTC_BOOTSTRAP=1 lets the stable
# compiler accept them. `-s none` turns AddressSanitizer off (it needs -Zsanitizer and the
# readers are safe Rust); coverage instrumentation (sancov), debug assertions and overflow checks
# stay on. New corpus entries go to fuzz/corpus/<target>/ (git-ignored except the seed_* files),
# crashes to fuzz/artifacts/<target>/, one log per target to fuzz/logs/<target>.log.
set -euo pipefail

secs="${1:-60}"
shift || true
cd "$(dirname "$0")"
if [ "$#" -gt 0 ]; then
    targets=("$@")
else
    targets=(csv_table job tif_csv map_xyz map_npy map_zygo_dat map_zygo_datx map_four_d_h5)
fi
export RUSTC_BOOTSTRAP="${RUSTC_BOOTSTRAP:-1}"

command -v cargo-fuzz >/dev/null || {
    echo "cargo-fuzz is not installed: cargo install cargo-fuzz" >&2
    exit 2
}

nice -n 10 cargo fuzz build -s none
mkdir -p logs
status=0
for t in "${targets[@]}"; do
    mkdir -p "corpus/$t" "artifacts/$t"
    echo "=== $t: ${secs} s ==="
    if ! nice -n 10 cargo fuzz run -s none "$t" "corpus/$t" -- \
        -max_total_time="$secs" -print_final_stats=1 >"logs/$t.log" 2>&1; then
        echo "$t: FAILED (crash or build error), see fuzz/logs/$t.log and fuzz/artifacts/$t/" >&2
        status=1
    fi
    # The summary: last coverage line and libFuzzer's final statistics.
    grep -E '^#[0-9]+[[:space:]]+DONE' "logs/$t.log" | tail -n 1 || true
    grep -E '^stat::(number_of_executed_units|average_exec_per_sec|new_units_added|peak_rss_mb)' \
        "logs/$t.log" || true
done
exit "$status"
