#!/usr/bin/env bash
# The README's test command: the Rust workspace's tests, then the Python package built into
# .venv and its pytest suite.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo test --workspace --release
python/test.sh
