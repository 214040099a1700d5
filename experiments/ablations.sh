#!/usr/bin/env bash
# The reach study's ablations (what explains the gaps to the paper), each a configuration the CLI
# runs, SEEDS seeds per cell (default 32), scenarios A and A,B, on one GPU:
#
#   bash experiments/ablations.sh OUT [gmr|mdgps|both]
#
# GMR: with the encoder bound (the default) and as the paper describes it (no bound); the
# paper's plant (its Gazebo arm had no effective torque limit) against the Jaco's peak torques;
# alpha 0.1 and 10 against 1. MDGPS: the plain MLP, the MLP with GMR's bound on its input, and
# the paper's plant. The 0.1 threshold (the paper's text) against 0.01 (its table) is in every
# summary. Each cell runs through experiments/gmr_sweep.sh (side by side, then
# experiments.diagnose); the table with intervals over seeds ends in OUT/ablations.md
# (experiments.intervals). The GMR half and the MDGPS half each fill a GPU for several minutes:
# run them as two commands where one command's time is limited.
set -u
OUT=${1:?usage: bash experiments/ablations.sh OUT [gmr|mdgps|both]}
WHICH=${2:-both}
export SEEDS=${SEEDS:-32} SCENARIO=${SCENARIO:-A,AB}
HERE=$(dirname "$0")
if [ "$WHICH" = gmr ] || [ "$WHICH" = both ]; then
  ALGORITHM=gmr bash "$HERE/gmr_sweep.sh" "$OUT/gmr" \
    "bound=" \
    "no_bound=--set gmr__encoder_squash=0.0" \
    "no_torque_limit=--set sim__clip_torques=False" \
    "alpha0.1=--set gmr__alpha=0.1" \
    "alpha10=--set gmr__alpha=10.0"
fi
if [ "$WHICH" = mdgps ] || [ "$WHICH" = both ]; then
  ALGORITHM=mdgps bash "$HERE/gmr_sweep.sh" "$OUT/mdgps" \
    "plain=" \
    "bound=--set mlp__input_squash=1.0" \
    "no_torque_limit=--set sim__clip_torques=False"
fi
python -m experiments.intervals "$OUT"/*/*/results.json > "$OUT/ablations.md"
cat "$OUT/ablations.md"
