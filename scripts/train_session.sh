#!/usr/bin/env bash
# Continue training the shipped model for one working session, in the background.
#
#   scripts/train_session.sh MINUTES [THREADS]      e.g.  scripts/train_session.sh 150 1
#
# 1. makes the training shards (seed 1, 4096 pairs) and held-out shards (seed 2, 256 pairs) under
#    $DATA (default /work/data) if they are not there yet (resumable; ~13 min on 2 cores);
# 2. trains from the committed checkpoint (polycubenet/checkpoints/polycubenet-cpu.pt: its EMA weights,
#    a fresh optimizer with a short warm-up) with the recipe recorded in it, into $RUN (default
#    /work/run-session), stopping cleanly after MINUTES;
# 3. publish and commit with:   scripts/publish_checkpoint.sh $RUN
# Re-running the same command resumes $RUN/last.pt.  Log: $RUN/train.out.
set -euo pipefail
cd "$(dirname "$0")/.."
MINUTES=${1:?minutes of training}
THREADS=${2:-1}
DATA=${DATA:-/work/data}
RUN=${RUN:-/work/run-session}
PY=${PY:-.venv/bin/python}
# learning-rate schedule: cosine from LR to LR*MIN_LR_RATIO over STEPS (defaults: constant 3e-4)
LR=${LR:-3e-4}
STEPS=${STEPS:-1000000}
MIN_LR_RATIO=${MIN_LR_RATIO:-1.0}
CKPT=polycubenet/checkpoints/polycubenet-cpu.pt
mkdir -p "$RUN"
# the recipe the shipped checkpoint was trained with, as train flags
RECIPE=$("$PY" - "$CKPT" <<'EOF'
import sys, torch
s = torch.load(sys.argv[1], map_location="cpu", weights_only=False)
d, tc = s.get("diffusion") or {}, s.get("train_config") or {}
flags = ["--preset", tc.get("preset", "cpu"),
         "--prediction", d.get("prediction", "eps"), "--schedule", d.get("schedule", "cosine"),
         "--pairing", d.get("pairing", "random"), "--min-snr", str(d.get("min_snr") or 0),
         "--points", str(tc.get("points", 512)), "--batch", str(tc.get("batch", 12)),
         "--anchor-gain", str((s.get("model_config") or {}).get("anchor_gain", 0.0)),
         "--t-bias", str(tc.get("t_bias", 1.0))]
print(" ".join(flags))
EOF
)
setsid nohup bash -c "
  $PY -m polycubenet.synth --out $DATA/heldout --count 256 --seed 2 --n-cond 2048 --n-target 2048 --workers 2 --no-progress &&
  $PY -m polycubenet.synth --out $DATA/train --count 4096 --seed 1 --n-cond 2048 --n-target 2048 --workers 2 --no-progress &&
  $PY -m polycubenet.train --data $DATA/train --eval-data $DATA/heldout --out $RUN --init $CKPT \
      $RECIPE --steps $STEPS --lr $LR --min-lr-ratio $MIN_LR_RATIO --warmup 50 --threads $THREADS \
      --ckpt-every 100 --log-every 50 --no-progress --max-minutes $MINUTES
" > "$RUN/train.out" 2>&1 &
echo "training in the background: $RUN/train.out (recipe: $RECIPE)"
