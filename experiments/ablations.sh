#!/usr/bin/env bash
# The reach study's ablations (what explains the gaps to the paper), each a configuration the CLI
# runs, SEEDS seeds per cell (default 32), scenarios A and A,B, on one GPU:
#
#   bash experiments/ablations.sh OUT [gmr|mdgps|both] [CELL ...]
#
# GMR: with the encoder bound (the default) and as the paper describes it (no bound); the
# paper's plant (its Gazebo arm had no effective torque limit) against the Jaco's peak torques,
# with and without the bound; continuous joints' angle errors wrapped to [−π, π) in the success
# test and the cost (task.wrap_angles) against raw angles; the same random arm configurations
# with their continuous joints' angles within ±π of the target's (task.random_angles_around_target)
# against the reset distribution's [−π, π]; alpha 0.1 and 10 against 1. MDGPS: the plain MLP,
# the MLP with GMR's bound on its input, the paper's plant, wrapped angles, angles around the
# target, the toolbox's weight initialiser N(0, 0.01²) (with and without angles around the
# target). The
# 0.1 threshold (the paper's text) against 0.01 (its table) is in every summary. Naming CELLs
# runs only those (e.g. to split the work over several commands of limited time). Each cell runs
# through experiments/gmr_sweep.sh (side by side, then experiments.diagnose); the table with
# intervals over seeds of every cell in OUT ends in OUT/ablations.md (experiments.intervals).
# Environment: SEEDS, SCENARIO (A,AB), EXTRA (added to every run, e.g. "--precision float32").
set -u
OUT=${1:?usage: bash experiments/ablations.sh OUT [gmr|mdgps|both] [CELL ...]}
WHICH=${2:-both}
shift $(( $# < 2 ? $# : 2 ))
export SEEDS=${SEEDS:-32} SCENARIO=${SCENARIO:-A,AB}
HERE=$(dirname "$0")
GMR_CELLS=(
  "bound="
  "no_bound=--set gmr__encoder_squash=0.0"
  "no_torque_limit=--set sim__clip_torques=False"
  "no_bound_no_torque_limit=--set gmr__encoder_squash=0.0 --set sim__clip_torques=False"
  "wrap=--set task__wrap_angles=True"
  "around_target=--set task__random_angles_around_target=True"
  "no_bound_around_target=--set gmr__encoder_squash=0.0 --set task__random_angles_around_target=True"
  "alpha0.1=--set gmr__alpha=0.1"
  "alpha10=--set gmr__alpha=10.0"
)
MDGPS_CELLS=(
  "plain="
  "bound=--set mlp__input_squash=1.0"
  "no_torque_limit=--set sim__clip_torques=False"
  "wrap=--set task__wrap_angles=True"
  "around_target=--set task__random_angles_around_target=True"
  "toolbox_init=--set mlp__init=normal"
  "toolbox_init_around_target=--set mlp__init=normal --set task__random_angles_around_target=True"
)
# The cells of a list that are named on the command line (all when none is named).
select_cells() {
  local spec name want
  for spec in "$@"; do
    name=${spec%%=*}
    if [ ${#CHOSEN[@]} -eq 0 ]; then echo "$spec"; continue; fi
    for want in "${CHOSEN[@]}"; do [ "$want" = "$name" ] && echo "$spec"; done
  done
}
CHOSEN=("$@")
for algorithm in gmr mdgps; do
  [ "$WHICH" = "$algorithm" ] || [ "$WHICH" = both ] || continue
  if [ "$algorithm" = gmr ]; then cells=("${GMR_CELLS[@]}"); else cells=("${MDGPS_CELLS[@]}"); fi
  mapfile -t run < <(select_cells "${cells[@]}")
  [ ${#run[@]} -gt 0 ] || continue
  ALGORITHM=$algorithm bash "$HERE/gmr_sweep.sh" "$OUT/$algorithm" "${run[@]}"
done
python -m experiments.intervals --compact "$OUT"/*/*/results.json > "$OUT/ablations.md"
cat "$OUT/ablations.md"
