# Sourced by scripts/check.sh: lint while building. clippy-driver compiles the workspace's own
# crates (with every clippy lint, warnings denied) while dependencies are compiled by plain rustc,
# so the lint pass costs no second build of the dependencies (a `cargo clippy` check pass does,
# ~10 minutes cold on 2 cores). The linted artifacts sit beside the plain ones (another metadata
# hash), so `cargo run -- demo` and this script never rebuild each other's crates.
export RUSTC_WORKSPACE_WRAPPER="${RUSTC_WORKSPACE_WRAPPER:-$(command -v clippy-driver || true)}"
if [ -z "$RUSTC_WORKSPACE_WRAPPER" ]; then
  echo "clippy-driver is not installed (rustup component add clippy)" >&2
  exit 1
fi
export CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__"
