#!/usr/bin/env bash
# Continue training the shipped model for one working session, in the background.
#
#   scripts/train_session.sh MINUTES [THREADS]      e.g.  scripts/train_session.sh 150 1
#
# 1. makes the held-out shards (seed 2, 256 pairs) and the first training set (seed 1, 4096 pairs) under
#    $DATA (default /work/data) if they are not there yet (resumable; ~13 min on 2 cores);
# 2. trains from the committed checkpoint (polycubenet/checkpoints/polycubenet-cpu.pt: its EMA weights,
#    a fresh optimizer with a short warm-up; INIT=FILE starts from another file instead, e.g. an unpublished
#    run's last.pt) with the recipe recorded in the committed one, into $RUN (default
#    /work/run-session), stopping cleanly after MINUTES, on $DATA/mix: links to every training shard;
# 3. meanwhile, one more process makes the further training sets ($SETS: folder, link prefix, seed and
#    synth flags of each; by default seed 4; seed 5 with --cad-features: round bosses, an edge's slanted
#    chamfer; seed 6 also --whole-slants: a whole end cut by a slanted plane; seed 10 also --max-strength
#    0.35: machined-like, mild global maps; 8192 pairs each) and links each finished shard into $DATA/mix,
#    where the training picks it up (--reload-every 200), so training starts after the first set only;
# 4. publish and commit with:   scripts/publish_checkpoint.sh $RUN 1
# Re-running the same command resumes $RUN/last.pt.  Logs: $RUN/train.out, $RUN/data.out.
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
BATCH=${BATCH:-12}  # pairs per step on a CPU (a checkpoint trained on a GPU records its larger batch)
FIT=${FIT:-false}  # true: re-fit STEPS to the measured pace so the cosine ends with MINUTES
SEED=${SEED:-0}  # the pair draw of the run: another value for another session's run
CKPT=polycubenet/checkpoints/polycubenet-cpu.pt
INIT=${INIT:-$CKPT}  # the weights a new run starts from (default: the committed checkpoint)
mkdir -p "$RUN"
# the recipe the shipped checkpoint was trained with, as train flags
RECIPE=$("$PY" -c "import sys; from polycubenet.train import recipe_flags; print(' '.join(recipe_flags(sys.argv[1])))" "$CKPT")
SYNTH="$PY -m polycubenet.synth --n-cond 2048 --n-target 2048 --no-progress"
link() {  # link() SRC PREFIX: every finished shard of SRC into $DATA/mix as shard-PREFIX<n>.npz
  echo "for f in $DATA/$1/shard-*.npz; do [ -e \$f ] || continue; b=\$(basename \$f); \
        [ -e $DATA/mix/shard-$2\${b#shard-} ] || ln -s \$f $DATA/mix/shard-$2\${b#shard-}; done"
}
mkdir -p "$DATA/mix"
setsid nohup bash -c "
  $SYNTH --out $DATA/heldout --count 256 --seed 2 --workers 2 &&
  $SYNTH --out $DATA/train --count 4096 --seed 1 --workers 2 && $(link train 0) &&
  $PY -m polycubenet.train --data $DATA/mix --eval-data $DATA/heldout --out $RUN --init $INIT \
      $RECIPE --batch $BATCH --steps $STEPS --lr $LR --min-lr-ratio $MIN_LR_RATIO --fit-steps $FIT --warmup 50 --threads $THREADS \
      --seed $SEED --reload-every 200 --ckpt-every 100 --log-every 50 --no-progress --max-minutes $MINUTES
" > "$RUN/train.out" 2>&1 &
# the further sets: "FOLDER PREFIX SEED [synth flags]" separated by ';' (8192 pairs each)
D_SETS="train4 1 4; train5cad 2 5 --cad-features; train6ws 6 6 --cad-features --whole-slants"
D_SETS="$D_SETS; train10m 7 10 --cad-features --whole-slants --max-strength 0.35"
SETS=${SETS:-$D_SETS}
LINKS="" MAKE=""
IFS=';' read -ra _sets <<< "$SETS"
for spec in "${_sets[@]}"; do
  read -r folder prefix seed flags <<< "$spec"
  LINKS="$LINKS $(link "$folder" "$prefix");"
  MAKE="$MAKE $SYNTH --out $DATA/$folder --count 8192 --seed $seed --workers 1 $flags;"
done
# one process, each shard linked as soon as it is written (the training re-reads the folder)
setsid nohup bash -c "
  while [ ! -e $DATA/mix/shard-000000.npz ]; do sleep 30; done
  ( while true; do $LINKS sleep 60; done ) & L=\$!
  $MAKE
  sleep 61; kill \$L
" > "$RUN/data.out" 2>&1 &
echo "training in the background: $RUN/train.out, more data: $RUN/data.out (recipe: $RECIPE)"
