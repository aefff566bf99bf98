#!/usr/bin/env bash
# The one check script, for developers and CI: formatting, lints, every test, doc tests.
set -euo pipefail
cd "$(dirname "$0")/.."

# A build that fills the disk fails in odd places (a linker's "Bus error", a truncated rlib): say so
# at the start when space is short, and again at the end when a step failed with the disk nearly full.
target_dir="${CARGO_TARGET_DIR:-target}"
mkdir -p "$target_dir"
free_mib() { df -Pm "$target_dir" | awk 'NR==2 {print $4}'; }
if [ "$(free_mib)" -lt 20480 ]; then
  echo "warning: $(free_mib) MiB free on the disk holding $target_dir; a cold build and the tests need about 20 GiB" >&2
fi
trap 'rc=$?; if [ "$rc" -ne 0 ] && [ "$(free_mib)" -lt 2048 ]; then echo "check.sh failed with only $(free_mib) MiB free on the disk holding $target_dir: the failure above is likely the disk filling" >&2; fi' EXIT

# Every system package the tests need: installed, or named and the script stops (system-deps.sh).
source scripts/system-deps.sh

if ! python3 -c "import duckdb" 2>/dev/null; then
  echo "installing duckdb (PyPI) for the plain-Parquet reader test"
  python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore duckdb ||
    python3 -m pip install --quiet --disable-pip-version-check --break-system-packages duckdb
fi
if ! python3 -c "import adbc_driver_flightsql.dbapi, pyarrow" 2>/dev/null; then
  echo "installing adbc-driver-flightsql and pyarrow (PyPI) for the Flight SQL client test"
  python3 -m pip install --quiet --disable-pip-version-check --root-user-action=ignore adbc-driver-flightsql pyarrow ||
    python3 -m pip install --quiet --disable-pip-version-check --break-system-packages adbc-driver-flightsql pyarrow
fi
if ! command -v cargo-nextest >/dev/null; then
  cargo install --locked cargo-nextest
fi

cargo fmt --all --check
# Every package of the lock file, for all targets: the layering test reads `cargo metadata --offline`.
cargo fetch --locked
# The demo's build (--no-default-features) and this one must give shared crates the same features.
python3 scripts/feature-pins.py --check
# Clippy lints the workspace's crates while they are built for the tests (see lint-env.sh): one
# build of the dependencies, shared with `cargo run -- demo`, and no separate check pass.
source scripts/lint-env.sh
cargo build --workspace --all-targets --locked
cargo nextest run --workspace --locked --no-fail-fast
# The same pictures on wgpu's GL backend (Mesa's llvmpipe, as on a machine with no Vulkan driver):
# the layer snapshots, against the same stored pictures, the README's figures and the demo's
# picture. The run above
# took the Vulkan adapter (lavapipe), which is preferred where both are installed.
# The whole workspace's build (no other feature set to compile), filtered to those tests.
WGPU_BACKEND=gl cargo nextest run --workspace --locked --no-fail-fast \
  -E 'binary_id(rtvtk-viz::layers) | binary_id(rtvtk-gpu::device) | binary_id(rtvtk::figures) | (binary_id(rtvtk::cli) & test(demo_draws_a_picture))'
cargo test --workspace --doc --locked
# The Python package: its wheel built and installed into a fresh venv, and its tests.
bash scripts/python-check.sh
