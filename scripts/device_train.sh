#!/usr/bin/env bash
# Train on a lent accelerator machine (the `device` tool: 16 cores, one GPU, a bare copy of this repository).
#
#   scripts/device_train.sh start MINUTES   # in the background (setsid): fresh training sets made on 14 cores
#                                           # while the GPU trains from the shipped checkpoint for MINUTES
#   scripts/device_train.sh export DIR      # the run's EMA weights (no optimizer: < 16 MiB) and logs into DIR
#   scripts/device_train.sh wait            # until the training has written its last checkpoint
#
# First (seconds): `python3 benchmarks/bench_train_step.py --data $D/mix --device cuda:0 --batches 128 512 2048`
# to see whether a step is launch-bound and which BATCH buys the most pairs per second.
# Run `start` under setsid from the first `run` call (`setsid nohup bash scripts/device_train.sh start 16 >
# /root/pc/main.out 2>&1 &`), then poll and `export $OUT` in each call: the machine goes back 30 s after a
# call ends, so issue the next call at once. NOGEN=1 restarts only the training. Session 7: 14 cores made
# 2 x 16384 uniform-sampled pairs in ~270 s (Poisson-disk ones will take longer: the numpy elimination);
# the training is CPU-bound (batch building; GPU ~1 % busy) at ~5 steps/s of 128.
#
# The data: two fresh sets (SEEDS; synth flags FLAGS1, default none, and FLAGS2, default --cad-features
# --whole-slants: round bosses, slanted ends, whole ends cut by slanted planes), COUNT pairs each, made shard by
# shard and linked into
# $D/mix, which the training re-reads every 200 steps (each shard's arrays are loaded once). The recipe: the
# shipped checkpoint's, with a GPU-sized batch (BATCH, default 128) and a cosine from LR to ~1e-5 that
# --fit-steps fits to the time given (EXTRA: further train flags after the recipe's, e.g. "--points 2048";
# RUNDIR: the run folder, default $D/run). Bring the exported last.pt back, then here:
#   scripts/publish_checkpoint.sh <its folder> 1
set -uo pipefail
cd "$(dirname "$0")/.."
D=${D:-/root/pc}
PY=${PY:-python3}
BATCH=${BATCH:-128}
LR=${LR:-3e-4}
MIN_LR_RATIO=${MIN_LR_RATIO:-0.033}
SEEDS=${SEEDS:-8 9}  # the generator seeds of the two fresh sets (FLAGS1, FLAGS2): new ones each lease
FLAGS1=${FLAGS1:-}  # synth flags of the first set (e.g. "--cad-features --whole-slants --max-strength 0.35")
FLAGS2=${FLAGS2:---cad-features --whole-slants}  # of the second (session 11 used --cad-features alone)
COUNT=${COUNT:-16384}  # pairs per set (the training uses what exists so far)
# PER_SHARD (default 256): pairs per shard; 64 lets a short lease start training within ~40 s.
# MINSHARDS (default 12): finished shards the training waits for; WORKERS (default 7): processes per set
CKPT=polycubenet/checkpoints/polycubenet-cpu.pt  # its recipe is the run's
INIT=${INIT:-$CKPT}  # the weights the run starts from, e.g. the committed continue file
EVAL=${EVAL:-}  # a held-out shard folder carried along (its loss is logged)
EXTRA=${EXTRA:-}  # further train flags, after the recipe's (e.g. "--points 2048": they win)
R=${RUNDIR:-$D/run}  # the run folder
mkdir -p "$D/mix" "$R"
case "${1:?start|export|wait}" in
start)
  MINUTES=${2:?minutes}
  nproc; nvidia-smi -L 2>/dev/null
  # the device image has no open3d: Poisson-disk sampling falls back to polycubenet.sampling.eliminate_samples
  # (the same points, ~5x slower; session 7 ran before it existed, with --sampler uniform)
  SYNTH="$PY -m polycubenet.synth --n-cond 2048 --n-target 2048 --per-shard ${PER_SHARD:-256} --no-progress ${SAMPLER:+--sampler $SAMPLER}"
  read -r S1 S2 <<< "$SEEDS"
  [ -n "${NOGEN:-}" ] || setsid nohup $SYNTH --out "$D/g$S1" --count "$COUNT" --seed "$S1" --workers ${WORKERS:-7} $FLAGS1 > "$D/g$S1.out" 2>&1 &
  [ -n "${NOGEN:-}" ] || setsid nohup $SYNTH --out "$D/g$S2" --count "$COUNT" --seed "$S2" --workers ${WORKERS:-7} $FLAGS2 > "$D/g$S2.out" 2>&1 &
  [ -n "${NOGEN:-}" ] || setsid nohup bash -c "while true; do for s in $S1 $S2; do for f in $D/g\$s/shard-*.npz; do [ -e \$f ] || continue;
      b=\$(basename \$f); [ -e $D/mix/shard-\$s\${b#shard-} ] || ln -s \$f $D/mix/shard-\$s\${b#shard-}; done; done;
      sleep 5; done" > /dev/null 2>&1 &
  while [ "$(ls "$D/mix" | wc -l)" -lt "${MINSHARDS:-12}" ]; do sleep 5; done
  RECIPE=$("$PY" -c "import sys; from polycubenet.train import recipe_flags; print(' '.join(recipe_flags(sys.argv[1])))" "$CKPT")
  echo "recipe: $RECIPE $EXTRA --batch $BATCH --lr $LR --init $INIT"
  $PY -m polycubenet.train --data "$D/mix" --out "$R" --init "$INIT" $RECIPE $EXTRA --batch "$BATCH" ${EVAL:+--eval-data $EVAL} \
      --lr "$LR" --min-lr-ratio "$MIN_LR_RATIO" --warmup 300 --steps 100000 --fit-steps True --device "${DEVICE:-cuda:0}" --seed ${TSEED:-8} \
      --reload-every "${RELOAD:-1000}" --ckpt-every 250 --log-every 100 --no-progress --max-minutes "$MINUTES"
  echo "training done"
  ;;
export)
  OUTDIR=${2:?folder}
  $PY - "$R/last.pt" "$OUTDIR/last.pt" <<'PYEOF'
import sys, torch
s = torch.load(sys.argv[1], map_location="cpu", weights_only=False)
for k in ("optimizer", "model"):
    s.pop(k, None)
torch.save(s, sys.argv[2])
print("exported step", s["step"], s.get("metrics"))
PYEOF
  cp "$R/log.jsonl" "$OUTDIR/" 2>/dev/null; tail -c 20000 "$D/main.out" > "$OUTDIR/main.out" 2>/dev/null
  tail -qn 1 "$D"/g*.out; ls "$D/mix" | wc -l
  ;;
wait)
  while ! grep -q "training done" "$D/main.out"; do sleep 5; done
  ;;
esac
