#!/usr/bin/env bash
# The Python package (python/, issue 42), as a user gets it: its abi3 wheel built by maturin on
# this target directory (dev profile: the dependencies the Rust tests just built), installed into a
# fresh venv with its dependencies from PyPI, then its pytest suite (which runs the CLI built
# beside it to compare pictures and `rtvtk check`). Called by scripts/check.sh.
set -euo pipefail
cd "$(dirname "$0")/.."

target="${CARGO_TARGET_DIR:-$PWD/target}"
venv="$target/python-venv"
rm -rf "$venv" "$target/wheels"
if ! python3 -m venv "$venv"; then
  echo "python3 cannot make a venv: install python3-venv (scripts/system-deps.sh names it)" >&2
  exit 1
fi
pip=("$venv/bin/pip" install --quiet --disable-pip-version-check)
"${pip[@]}" "maturin>=1.5,<2" pytest pyarrow numpy pandas duckdb
"$venv/bin/maturin" build --quiet --manifest-path python/Cargo.toml --profile dev --compatibility linux \
  --interpreter "$venv/bin/python" --out "$target/wheels"
"${pip[@]}" "$target"/wheels/rtvtk-*.whl
RTVTK_BIN="$target/debug/rtvtk" "$venv/bin/python" -m pytest -q python/tests
