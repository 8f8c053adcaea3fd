#!/usr/bin/env bash
# Builds the release distributions of the Python package `preston-dwell` (import name `preston`)
# into target/dist: the sdist and an abi3 wheel for CPython 3.9+ on Linux x86_64 tagged
# manylinux2014 (glibc 2.17: RHEL/CentOS 7 and every newer distribution), linked by zig (the
# `ziglang` package from PyPI) so that the host's glibc does not matter; then checks the wheel's
# tag and external libraries with auditwheel, and installs it into a fresh virtual environment
# with no Rust toolchain on PATH to import it, compare `preston.__version__` and the wheel's
# `preston --version` with the command line's version, and solve the sample job the wheel ships,
# outside the checkout (docs/install.md). Needs python3 (>= 3.9) with venv and pip, cargo with Rust 1.89
# or newer, and crates.io and PyPI reachable.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
VENV=target/build-wheels-venv
if [ ! -x "$VENV/bin/python" ]; then
    "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install --quiet --upgrade pip
"$VENV/bin/python" -m pip install --quiet "maturin>=1.9,<2" ziglang auditwheel
rm -rf target/dist
# maturin finds zig through `python -m ziglang` of the interpreter on PATH.
PATH="$PWD/$VENV/bin:$PATH" CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-target/zig}" \
    "$VENV/bin/maturin" build --release --zig --compatibility manylinux2014 --out target/dist
"$VENV/bin/maturin" sdist --out target/dist
"$VENV/bin/auditwheel" show target/dist/preston_dwell-*.whl
# A clean environment, no Rust: only /usr/bin and /bin on PATH.
rm -rf target/clean-venv
"$PY" -m venv target/clean-venv
target/clean-venv/bin/python -m pip install --quiet target/dist/preston_dwell-*.whl
# The command line's version without building it: from a binary already built, else from the
# sources (`cargo metadata` compiles nothing).
if [ -x target/release/preston ]; then
    cli_version="$(target/release/preston --version | awk '{print $2}')"
else
    cli_version="$(cargo metadata --no-deps --format-version 1 | "$PY" -c \
        'import json, sys; print(next(p["version"] for p in json.load(sys.stdin)["packages"] if p["name"] == "preston-cli"))')"
fi
clean_bin="$PWD/target/clean-venv/bin"
elsewhere="$(mktemp -d)"
trap 'rm -rf "$elsewhere"' EXIT
(cd "$elsewhere" && env -i PATH=/usr/bin:/bin HOME="$HOME" "$clean_bin/python" - "$cli_version" "$clean_bin/preston" <<'PY'
import shutil, subprocess, sys
import preston
assert shutil.which("cargo") is None and shutil.which("rustc") is None, "Rust on PATH"
assert preston.__version__ == sys.argv[1], (preston.__version__, sys.argv[1])
# The wheel's command line: the same version.
v = subprocess.run([sys.argv[2], "--version"], capture_output=True, text=True, check=True).stdout
assert v == f"preston {sys.argv[1]}\n", v
# The sample job shipped in the wheel, solved outside the checkout.
r = preston.solve(preston.sample_job("sample"))
print(f"preston {preston.__version__}: sample job RMS {r.report['rms_before_nm']:.2f} -> "
      f"{r.report['rms_after_nm']:.2f} nm, status {r.report['status']}")
PY
)
