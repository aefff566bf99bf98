#!/usr/bin/env bash
# Runs the proptest harnesses at depth: each for CASES cases, split over consecutive fixed seeds
# (PROPTEST_RNG_SEED = FIRST_SEED, FIRST_SEED+1, ...; a run is reproducible by its seed), and
# prints each harness's cases per second. A failing case is shrunk by proptest and kept in the
# harness's `regressions` file beside its source: commit it with the fix (CI then replays it).
#
#   bash scripts/fuzz.sh [CASES per harness, default 100000] [FIRST_SEED, default 1] [HARNESS...]
#
# Harnesses: reader (damaged datasets: store/tests/dataset.rs), c_abi (any sequence of C calls:
# rl-writer/tests/c_abi.rs), functions (the ray functions on any values: query/src/functions).
# CI runs each at proptest's default of 256 cases through scripts/check.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
# The same build as scripts/check.sh's tests (linted artifacts), so nothing is compiled twice.
source scripts/lint-env.sh

cases="${1:-100000}"
first_seed="${2:-1}"
shift $(($# > 2 ? 2 : $#))
harnesses=("$@")
[ ${#harnesses[@]} -eq 0 ] && harnesses=(reader c_abi functions)
# Cases per seed: a seed's run is one test process (its start is under a second; runs are kept
# long all the same).
per_run="${RTVTK_FUZZ_CASES_PER_SEED:-10000}"

# Each harness as a nextest filter: the workspace's own build (what scripts/check.sh builds), so
# nothing is compiled again (`cargo test -p` alone would unify features differently and rebuild
# the dependencies).
harness_filter() {
  case "$1" in
    reader) echo "binary_id(rtvtk-store::dataset) & test(/damaged_datasets_give_errors_not_panics$/)" ;;
    c_abi) echo "binary_id(rl::c_abi) & test(/any_call_sequence_gives_errors_or_a_sound_trace$/)" ;;
    functions) echo "binary_id(rtvtk-query) & test(/ray_functions_never_panic_and_give_null_for_non_finite_input$/)" ;;
    *) echo "unknown harness $1: expected reader, c_abi or functions" >&2; exit 2 ;;
  esac
}

cargo build --workspace --all-targets --locked -q
for h in "${harnesses[@]}"; do
  filter="$(harness_filter "$h")"
  done_cases=0
  seed="$first_seed"
  start=$(date +%s.%N)
  while [ "$done_cases" -lt "$cases" ]; do
    n=$((cases - done_cases < per_run ? cases - done_cases : per_run))
    if ! PROPTEST_CASES="$n" PROPTEST_RNG_SEED="$seed" cargo nextest run --workspace --locked --no-fail-fast \
      --status-level fail --final-status-level fail -E "$filter" >"/tmp/rtvtk-fuzz-$h.log" 2>&1; then
      echo "$h: FAILED at seed $seed (cases $done_cases..$((done_cases + n))); see /tmp/rtvtk-fuzz-$h.log" >&2
      tail -40 "/tmp/rtvtk-fuzz-$h.log" >&2
      exit 1
    fi
    if ! grep -q "1 test run: 1 passed" "/tmp/rtvtk-fuzz-$h.log"; then
      echo "$h: the filter ran no test ($filter); see /tmp/rtvtk-fuzz-$h.log" >&2
      exit 1
    fi
    done_cases=$((done_cases + n))
    seed=$((seed + 1))
  done
  end=$(date +%s.%N)
  python3 -c "import sys; c, s = int(sys.argv[2]), float(sys.argv[4]) - float(sys.argv[3]); print(f'{sys.argv[1]}: {c} cases, seeds {sys.argv[5]}..{sys.argv[6]}, {s:.1f} s, {c / s:.0f} cases/s, 0 failures')" \
    "$h" "$done_cases" "$start" "$end" "$first_seed" "$((seed - 1))"
done
