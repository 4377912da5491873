#!/usr/bin/env bash
# Paper 1 table 3's ablation, step 1: train the network on each energy (skeleton terms only; + foot;
# + interpenetration; the full energy), one after the other, on the training split (held-out clips and bodies
# kept out). Step 2 is `retarget eval --heldout ../shared/data/motions/cmu --ablation ...` (README).
# About 15 minutes per energy on the 2-core CPU, plus about 25 minutes once to build the training set (cached in
# ~/.cache/retarget/recurrent). OUT defaults to the shipped models folder; the full energy is the shipped
# recurrent.pt.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-retarget_core/data/models}
LOGS=${LOGS:-benchmarks/train/results}
for energy in full skeleton foot interpenetration; do
  name="recurrent-$energy"
  [ "$energy" = full ] && name=recurrent
  .venv/bin/retarget train recurrent --clips ../shared/data/motions/cmu --energy "$energy" \
    -o "$OUT/$name.pt" --log "$LOGS/train-$name.jsonl"
done
