#!/usr/bin/env bash
# Two training arms side by side on one lent GPU, from one init file, then both exported into $OUT
# (session 25's wide-model ablation). Run on the device from the repository root, as one `run` call:
#
#   here:   mkdir -p build/device && python -c "import sys, torch; s = torch.load(sys.argv[1], weights_only=False);
#           [s.pop(k, None) for k in ('optimizer', 'model')]; torch.save(s, 'build/device/wide.pt')" RUN/last.pt
#   device: run(command="bash scripts/device_two_arms.sh", carry=["build/device"], timeout_s=570)
#
# Arm w512: batch 256 x 512 points; arm w2048: batch 128 x 2048 points; both with ARM_FLAGS (default the
# wide-write preset), lr LR -> 1e-5 fitted to MINUTES, on fresh pairs (SEEDS) made by 12 of its cores while
# they train (scripts/device_train.sh). Stops polling after DEADLINE seconds and exports what exists.
export D=/root/pc PYTHONUNBUFFERED=1
mkdir -p $D
T0=$(date +%s)
nproc; nvidia-smi -L
W=${ARM_FLAGS:---preset cpu-anchored-normals-wide-write}
INIT=${INIT:-build/device/wide.pt} LR=${LR:-8e-5} MINUTES=${MINUTES:-6.8} SEEDS=${SEEDS:-70 71}
env INIT=$INIT BATCH=256 LR=$LR MIN_LR_RATIO=0.125 SEEDS="$SEEDS" PER_SHARD=64 WORKERS=6 RUNDIR=$D/w512 \
    EXTRA="$W" setsid nohup bash scripts/device_train.sh start $MINUTES > $D/w512.out 2>&1 &
env NOGEN=1 INIT=$INIT BATCH=128 LR=$LR MIN_LR_RATIO=0.125 RUNDIR=$D/w2048 \
    EXTRA="$W --points 2048" setsid nohup bash scripts/device_train.sh start $MINUTES > $D/w2048.out 2>&1 &
while true; do
  sleep 30; el=$(( $(date +%s) - T0 ))
  echo "t=$el s shards=$(ls $D/mix | wc -l)"; for a in w512 w2048; do tail -n 1 $D/$a/log.jsonl 2>/dev/null | cut -c1-200; done
  if grep -q "training done" $D/w512.out && grep -q "training done" $D/w2048.out; then break; fi
  [ $el -gt ${DEADLINE:-505} ] && { echo "deadline"; break; }
done
for a in w512 w2048; do mkdir -p $OUT/$a; RUNDIR=$D/$a bash scripts/device_train.sh export $OUT/$a; cp $D/$a.out $OUT/$a/main.out; done
read -r S1 S2 <<< "$SEEDS"; tail -n 3 $D/g$S1.out $D/g$S2.out; ls -la $OUT/*
echo "total $(( $(date +%s) - T0 )) s"
