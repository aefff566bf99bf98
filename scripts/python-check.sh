#!/usr/bin/env bash
# The Python package (python/, issue 42), as a user gets it: `pip install ./python` (pip's own
# PEP 517 build: maturin fetched into an isolated build environment) into a fresh venv, then its
# pytest suite, which runs the CLI built beside it to compare pictures, reports and `rtvtk check`.
# The wheel is built with the dev profile on this target directory (MATURIN_PEP517_ARGS), so it
# reuses the dependencies the Rust tests just built; a user's plain `pip install ./python` builds
# the release profile the same way. Called by scripts/check.sh.
set -euo pipefail
cd "$(dirname "$0")/.."

target="${CARGO_TARGET_DIR:-$PWD/target}"
venv="$target/python-venv"
rm -rf "$venv"
if ! python3 -m venv "$venv"; then
  echo "python3 cannot make a venv: install python3-venv (scripts/system-deps.sh names it)" >&2
  exit 1
fi
pip=("$venv/bin/pip" install --quiet --disable-pip-version-check)
"${pip[@]}" --upgrade pip
"${pip[@]}" pytest pandas duckdb pillow
# With the optional Mitsuba 3 dependency (rtvtk.mitsuba and its tests).
CARGO_TARGET_DIR="$target" MATURIN_PEP517_ARGS="--profile dev --compatibility linux" "${pip[@]}" "./python[mitsuba]"
"$venv/bin/python" -c "import rtvtk, sys; print('rtvtk', rtvtk.__version__, 'installed in', sys.prefix)"
# `import rtvtk` is the installed package: python/ itself is not on sys.path.
RTVTK_BIN="$target/debug/rtvtk" "$venv/bin/python" -m pytest -q python/tests
