#!/usr/bin/env bash
# Two training arms side by side on one lent GPU, from one init file, then both exported into $OUT
# (session 25's wide-model ablation; session 32's data ablation). Run on the device from the repository root,
# as one `run` call:
#
#   here:   mkdir -p build/device && python -c "import sys, torch; s = torch.load(sys.argv[1], weights_only=False);
#           [s.pop(k, None) for k in ('optimizer', 'model')]; torch.save(s, 'build/device/wide.pt')" RUN/last.pt
#   device: run(command="bash scripts/device_two_arms.sh", carry=["build/device"], timeout_s=570)
#
# Each arm trains with its own flags (A_EXTRA, B_EXTRA; default the wide-write preset, arm B at 2048 points)
# and batch (A_BATCH 256, B_BATCH 128), lr LR -> LR * MIN_LR_RATIO fitted to MINUTES, on fresh pairs made by
# the machine's cores while they train (scripts/device_train.sh): arm A's two sets (SEEDS; FLAGS1, FLAGS2) and,
# where B_SEEDS is set, arm B's own two sets (B_SEEDS; B_FLAGS1, B_FLAGS2) in their own folder; otherwise arm B
# reads arm A's pairs. Stops polling after DEADLINE seconds and exports what exists into $OUT/A_NAME, B_NAME.
export PYTHONUNBUFFERED=1
T0=$(date +%s)
nproc; nvidia-smi -L 2>/dev/null
W=${ARM_FLAGS:---preset cpu-anchored-normals-wide-write}
A=${A_NAME:-w512} B=${B_NAME:-w2048}
INIT=${INIT:-build/device/wide.pt} LR=${LR:-8e-5} MINUTES=${MINUTES:-6.8} SEEDS=${SEEDS:-70 71}
DA=/root/pc DB=/root/pc BGEN=(NOGEN=1)  # arm B reads arm A's pairs, unless it has its own seeds
if [ -n "${B_SEEDS:-}" ]; then
  DB=/root/pcB BGEN=(SEEDS="$B_SEEDS" FLAGS1="${B_FLAGS1:-}" FLAGS2="${B_FLAGS2:---cad-features --whole-slants}")
fi
mkdir -p $DA $DB
env D=$DA INIT=$INIT BATCH=${A_BATCH:-256} LR=$LR MIN_LR_RATIO=${MIN_LR_RATIO:-0.125} SEEDS="$SEEDS" PER_SHARD=64 \
    WORKERS=${WORKERS:-6} RUNDIR=$DA/$A EXTRA="${A_EXTRA-$W}" \
    setsid nohup bash scripts/device_train.sh start $MINUTES > $DA/$A.out 2>&1 &
env D=$DB "${BGEN[@]}" INIT=$INIT BATCH=${B_BATCH:-128} LR=$LR MIN_LR_RATIO=${MIN_LR_RATIO:-0.125} PER_SHARD=64 \
    WORKERS=${WORKERS:-6} RUNDIR=$DB/$B EXTRA="${B_EXTRA-$W --points 2048}" \
    setsid nohup bash scripts/device_train.sh start $MINUTES > $DB/$B.out 2>&1 &
while true; do
  sleep 30; el=$(( $(date +%s) - T0 ))
  echo "t=$el s shards=$(ls $DA/mix | wc -l) $(ls $DB/mix | wc -l)"
  tail -n 1 $DA/$A/log.jsonl 2>/dev/null | cut -c1-200; tail -n 1 $DB/$B/log.jsonl 2>/dev/null | cut -c1-200
  if grep -q "training done" $DA/$A.out && grep -q "training done" $DB/$B.out; then break; fi
  [ $el -gt ${DEADLINE:-505} ] && { echo "deadline"; break; }
done
mkdir -p $OUT/$A $OUT/$B
D=$DA RUNDIR=$DA/$A bash scripts/device_train.sh export $OUT/$A; cp $DA/$A.out $OUT/$A/main.out
D=$DB RUNDIR=$DB/$B bash scripts/device_train.sh export $OUT/$B; cp $DB/$B.out $OUT/$B/main.out
tail -n 3 $DA/g*.out $DB/g*.out; ls -la $OUT/*
echo "total $(( $(date +%s) - T0 )) s"
