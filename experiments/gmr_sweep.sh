#!/usr/bin/env bash
# The GMR robustness study on scenario A: one configuration change at a time, 6 seeds each, all
# runs side by side on one GPU, each followed by `python -m experiments.diagnose`.
#
#   bash experiments/gmr_sweep.sh OUT [NAME=--set ... ...]
#
# Without NAME=ARGS pairs it runs the default list below. Results: OUT/NAME/{summary.md,
# results.json, diagnostics.md} and OUT/NAME.log. Environment: ALGORITHM (gmr), SCENARIO (A),
# SEEDS (6), EXTRA (arguments added to every run, e.g. "--iterations 2" for a smoke test).
set -u
OUT=${1:?usage: bash experiments/gmr_sweep.sh OUT [NAME=ARGS ...]}
shift
mkdir -p "$OUT"
if [ $# -eq 0 ]; then
  set -- "base=" \
         "alpha0.1=--set gmr__alpha=0.1" \
         "alpha10=--set gmr__alpha=10.0" \
         "floor0.3=--set sstep__obs_std_floor=0.3" \
         "floor1=--set sstep__obs_std_floor=1.0" \
         "autodiff=--set policy_linearization=autodiff"
fi
# Several processes share the GPU: no process may take most of its memory up front.
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.1}
ALGORITHM=${ALGORITHM:-gmr}
SCENARIO=${SCENARIO:-A}
SEEDS=${SEEDS:-6}
for spec in "$@"; do
  name=${spec%%=*}
  args=${spec#*=}
  (
    # shellcheck disable=SC2086  # args is a list of words on purpose
    python -m experiments.reach --algorithm "$ALGORITHM" --scenario "$SCENARIO" --seeds "$SEEDS" \
      --no-plots --out "$OUT/$name" $args ${EXTRA:-} > "$OUT/$name.log" 2>&1 \
      && python -m experiments.diagnose "$OUT/$name" >> "$OUT/$name.log" 2>&1
    echo "$name: exit $?" >> "$OUT/status.txt"
  ) &
done
wait
cat "$OUT/status.txt"
