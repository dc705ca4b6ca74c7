#!/usr/bin/env bash
# The third GPU lease (29 Nov): does a larger network see real cars better? Every `lite` recipe tried scores car AP
# 0.16-0.19 on the real scene-0523, and the docs named the `paper` preset (4.9 M parameters, 512x512 pillars) as
# what had not been scored there: lease 2 trained it 3 of 4 epochs and lost the checkpoint (58 MB, over the 16 MB
# a lease returns per file). This lease trains it alone on the GPU, from scratch, on 100 fresh seeds (300-399;
# ideal scans + scans with every sim-to-real effect and vegetation, as lease 2), a one-cycle schedule of
# P_EPOCHS epochs, and returns its weights split into parts of 15 MB (`cat P.pt.part* > P.pt` joins them).
#
#   OUT=dir [P_EPOCHS=5] [BUDGET_S=470] [PY=python3] [SMOKE=1] bash scripts/gpu_lease_paper.sh
#
# Writes into OUT: run.log, P_hist.json, P.pt.part00, P.pt.part01 (…; or P_ckpt.pt.part* when the budget ended the
# run first). SMOKE=1: a few scans and steps on the CPU (tests/detector/test_gpu_lease_scripts.py).
set -u
PY=${PY:-python3}
: "${OUT:?set OUT to the results folder}"
BUDGET_S=${BUDGET_S:-470}
SMOKE=${SMOKE:-0}
P_EPOCHS=${P_EPOCHS:-5}
T0=$(date +%s)
el() { echo $(( $(date +%s) - T0 )); }
W=${WORK:-/tmp/jg-lease3}
rm -rf "$W"; mkdir -p "$W" "$OUT"
exec > >(tee -a "$OUT/run.log") 2>&1
NCPU=$(nproc)
JG="$PY -m jitterguard.cli"
if [ "$SMOKE" = 1 ]; then
  DATA="--scenarios mixed --train-seeds 300-301 --val-seeds 900 --frames-per-scenario 2"; BATCH=2; P_EPOCHS=1
  EVERY=1; P_STEPS="--max-steps-per-epoch 1"  # one step of the paper network is what the CPU test can afford
else
  DATA="--train-seeds 300-399 --val-seeds 900-901 --frames-per-scenario 10"; BATCH=16; EVERY=200; P_STEPS=""
fi
DATA="$DATA --effects none+random,vegetation --rotation 45 --batch-size $BATCH --no-progress --fit-recalibration"
echo "== $(date -u) cores $NCPU budget ${BUDGET_S}s"
LAUNCH="$PY -m torch.distributed.run --standalone --nproc_per_node=1 -m jitterguard.cli"
$PY -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" || LAUNCH=$JG
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"

echo "== casting with $NCPU processes at $(el)s"
$JG train --out "$W/cast" $DATA --preset paper --epochs 1 --max-steps-per-epoch 1 --workers "$NCPU" \
  > "$W/cast.log" 2>&1 || { tail -20 "$W/cast.log"; exit 1; }
mkdir -p "$W/P"; for c in "$W"/cast/cache-*; do ln -s "$c" "$W/P/"; done
LEFT=$(( BUDGET_S - $(el) - 15 ))
echo "== at $(el)s: P (paper, from scratch) $P_EPOCHS epochs, $LEFT s left"
timeout "$LEFT" $LAUNCH train --out "$W/P" $DATA --preset paper --lr 3e-3 --epochs "$P_EPOCHS" --seed 9 \
  --workers $(( NCPU - 2 > 1 ? NCPU - 2 : 1 )) --checkpoint-every "$EVERY" $P_STEPS > "$W/P.log" 2>&1
echo "P exit $? at $(el)s"
grep -E "epoch|weights|step" "$W/P.log" | tail -n 20
cp "$W/P/history.json" "$OUT/P_hist.json" 2>/dev/null
F="$W/P/weights.pt"; NAME=P.pt
[ -f "$F" ] || { F="$W/P/checkpoint.pt"; NAME=P_ckpt.pt; }
[ -f "$F" ] && split -b 15M -d "$F" "$OUT/$NAME.part" && sha256sum "$F"
echo "== done at $(el)s"; ls -la "$OUT"
