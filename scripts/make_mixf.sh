#!/usr/bin/env bash
# The main line's training mix (MIXF, model card sessions 52-54) on a fresh machine, round robin, into $DATA.
#
#   scripts/make_mixf.sh            (DATA=/work/data by default; ~45 minutes on one core)
#
# Writes the held-out shards ($DATA/heldout: seed 2, 256 pairs) first, then 256 pairs a round from each of MIXF's
# five sources, linking every finished shard into $DATA/mixf as it is written, so that a run started on the
# growing folder (`python -m polycubenet.train --data $DATA/mixf --reload-every 50 ...`) can begin after the
# first round:
#   seed 1, 3072 pairs (shard-0*) | seed 6 --cad-features --whole-slants, 3072 (shard-6*) |
#   seed 13 --turned 1.0 --bolt-circles 0.75, 1536 (shard-c-*) |
#   seeds 14 and 15 --turned 1.0 --bolt-circles 0.75 --flanges 1.0, 768 each (shard-d-14-*, shard-d-15-*).
# Pair i of a seed does not depend on the count asked for, so each round's larger --count only adds a shard, and
# re-running the script resumes.  9216 training pairs in 36 shards, 2048 points each.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${DATA:-/work/data}
PY=${PY:-.venv/bin/python}
S="$PY -m polycubenet.synth --n-cond 2048 --n-target 2048 --no-progress --workers 1"
mkdir -p "$DATA/mixf"
. scripts/link_shards.sh
link() { link_shards "$DATA/$1" "$DATA/mixf" "$2"; }  # link SRC PREFIX: SRC's finished shards into $DATA/mixf
$S --out "$DATA/heldout" --count 256 --seed 2
for r in $(seq 1 12); do
  n=$((256 * r))
  $S --out "$DATA/train" --count $n --seed 1 && link train 0
  $S --out "$DATA/train6ws" --count $n --seed 6 --cad-features --whole-slants && link train6ws 6
  if [ "$r" -le 6 ]; then
    $S --out "$DATA/turned13" --count $n --seed 13 --turned 1.0 --bolt-circles 0.75 && link turned13 c-
  fi
  if [ "$r" -le 3 ]; then
    for seed in 14 15; do
      $S --out "$DATA/flanges$seed" --count $n --seed $seed --turned 1.0 --bolt-circles 0.75 --flanges 1.0 &&
        link "flanges$seed" "d-$seed-"
    done
  fi
  echo "round $r of 12: $(ls "$DATA/mixf" | wc -l) shards in $DATA/mixf ($(date +%H:%M))"
done
