#!/usr/bin/env bash
# The second GPU lease of 28 Nov (after scripts/gpu_lease_train.sh): run B of the first lease (lite from scratch
# with every sim-to-real effect) scored best on the real scene, so this lease continues it on 100 fresh seeds
# (200-299), side by side with the same plus pitch/roll augmentation, and trains the `paper` preset from scratch
# on the same scans. The lite epochs fill BUDGET_S at EPOCH_S seconds an epoch: 80 for three runs side by side on
# an H200 machine with 16 cores (the lease of 28 Nov assumed 52, from two runs, and ran out in the 5th of 5
# epochs: 76 s measured); the paper run gets PAPER_EPOCHS and keeps its last checkpoint if the budget ends first.
# A paper checkpoint is 58 MB, over the 16 MB a lease returns per file: copy its weights, not its checkpoint.
#
#   OUT=dir INIT=B.pt [BUDGET_S=470] [PY=python3] [SMOKE=1] bash scripts/gpu_lease_continue.sh
#
# Writes into OUT: run.log, B2.pt, B2t.pt, P.pt (or *_ckpt.pt), and their *_hist.json (7 files).
set -u
PY=${PY:-python3}
: "${OUT:?set OUT to the results folder}"
: "${INIT:?set INIT to the weights to continue}"
BUDGET_S=${BUDGET_S:-470}
SMOKE=${SMOKE:-0}
PAPER_EPOCHS=${PAPER_EPOCHS:-4}
T0=$(date +%s)
el() { echo $(( $(date +%s) - T0 )); }
W=${WORK:-/tmp/jg-lease2}
rm -rf "$W"; mkdir -p "$W" "$OUT"
exec > >(tee -a "$OUT/run.log") 2>&1
NCPU=$(nproc)
JG="$PY -m jitterguard.cli"
if [ "$SMOKE" = 1 ]; then
  # one epoch each and one step of the paper network: what the CPU test can afford
  DATA="--scenarios mixed --train-seeds 200-201 --val-seeds 900 --frames-per-scenario 2"; BATCH=2; EPOCH_S=1000
  PAPER_EPOCHS=1; P_STEPS="--max-steps-per-epoch 1"
else
  DATA="--train-seeds 200-299 --val-seeds 900-901 --frames-per-scenario 10"; BATCH=16; EPOCH_S=${EPOCH_S:-80}
  P_STEPS=""
fi
DATA="$DATA --effects none+random,vegetation --rotation 45 --batch-size $BATCH --no-progress --fit-recalibration"
echo "== $(date -u) cores $NCPU budget ${BUDGET_S}s"
LAUNCH="$PY -m torch.distributed.run --standalone --nproc_per_node=1 -m jitterguard.cli"
$PY -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" || LAUNCH=$JG

echo "== casting with $NCPU processes at $(el)s"
$JG train --out "$W/cast" $DATA --init "$INIT" --epochs 1 --max-steps-per-epoch 1 --workers "$NCPU" \
  > "$W/cast.log" 2>&1 || { tail -20 "$W/cast.log"; exit 1; }
E=$(( (BUDGET_S - $(el) - 40) / EPOCH_S )); [ "$E" -lt 1 ] && E=1
LEFT=$(( BUDGET_S - $(el) - 12 ))
echo "== at $(el)s: B2 and B2t $E epochs, P $PAPER_EPOCHS epochs, $LEFT s left"
for r in B2 B2t P; do mkdir -p "$W/$r"; for c in "$W"/cast/cache-*; do ln -s "$c" "$W/$r/"; done; done
NW=$(( NCPU / 3 - 1 )); [ $NW -lt 1 ] && NW=1
timeout "$LEFT" $LAUNCH train --out "$W/B2" $DATA --init "$INIT" --lr 2e-3 --epochs "$E" --seed 6 --workers $NW \
  > "$W/B2.log" 2>&1 &
P1=$!
timeout "$LEFT" $LAUNCH train --out "$W/B2t" $DATA --init "$INIT" --lr 2e-3 --epochs "$E" --seed 7 --tilt-aug 2 \
  --workers $NW > "$W/B2t.log" 2>&1 &
P2=$!
timeout "$LEFT" $LAUNCH train --out "$W/P" $DATA --preset paper --lr 3e-3 --epochs "$PAPER_EPOCHS" --seed 8 \
  --workers $NW $P_STEPS > "$W/P.log" 2>&1 &
P3=$!
wait $P1; echo "B2 exit $? at $(el)s"; wait $P2; echo "B2t exit $? at $(el)s"; wait $P3; echo "P exit $? at $(el)s"
for r in B2 B2t P; do
  grep -E "epoch|weights" "$W/$r.log" | tail -n 12
  cp "$W/$r/history.json" "$OUT/${r}_hist.json" 2>/dev/null
  if [ -f "$W/$r/weights.pt" ]; then cp "$W/$r/weights.pt" "$OUT/$r.pt"; else cp "$W/$r/checkpoint.pt" "$OUT/${r}_ckpt.pt" 2>/dev/null; fi
done
echo "== done at $(el)s"; ls -la "$OUT"
