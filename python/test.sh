#!/usr/bin/env bash
# Builds the `preston` Python package into a local virtual environment (.venv at the repository
# root, created if missing) and runs its pytest suite. Needs python3 (>= 3.9) with venv and pip,
# and cargo; everything else comes from the package registries. Cargo's outputs go to
# CARGO_TARGET_DIR where it is set (target/ otherwise).
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -r python/requirements-test.txt
# The CLI the tests compare against (the wheel's own `preston` command is tested beside it).
cargo build --release -p preston-cli
cargo_target="${CARGO_TARGET_DIR:-target}"
case "$cargo_target" in /*) ;; *) cargo_target="$PWD/$cargo_target" ;; esac
rm -rf target/wheels
# A wheel for this host (pyproject.toml at the repository root; the release wheels for glibc
# 2.17, manylinux2014, are built by scripts/build-wheels.sh with zig).
.venv/bin/maturin build --release --compatibility linux --out target/wheels
.venv/bin/python -m pip install --quiet --force-reinstall --no-deps target/wheels/preston_dwell-*.whl
# From the repository root, so that the installed wheel (not python/preston) is imported.
PRESTON_BIN="$cargo_target/release/preston" .venv/bin/python -m pytest -q python/tests "$@"
