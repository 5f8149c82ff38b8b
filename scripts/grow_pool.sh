#!/usr/bin/env bash
# A training folder that keeps growing with pairs never drawn before: MIXF's shards plus new ones, written one
# shard (256 pairs) at a time while a run trains on the folder (`python -m polycubenet.train --data $DATA/mixs
# --reload-every 50 ...` picks each new shard up as it is linked).
#
#   scripts/grow_pool.sh [ROUNDS]      (DATA=/work/data; one round ~5 minutes of one core; default 40 rounds)
#
# Each round adds one shard of each of MIXF's two large sources under new seeds (seed 201 the plain pairs, seed
# 206 --cad-features --whole-slants), and every third round one turned shard (seed 213 --turned 1.0
# --bolt-circles 0.75) and one flanged shard (seed 214, --flanges 1.0 besides), each into $DATA/pool<seed>,
# linked into $DATA/mixs beside links to every MIXF shard present (none on a machine where scripts/make_mixf.sh
# has not run: then the folder holds only pairs never drawn before).  Pair i of a seed does not depend on the
# count asked for, so a round's larger --count only adds a shard,
# and re-running the script (or running it on a fresh machine) rebuilds the same pairs and resumes.  None of
# these seeds is a held-out seed (2, 9102, 9001, 9017).  SHIFT=K (environment) adds K to all four seeds (folders
# pool<seed>, links p<seed>-*), for pairs a line that already drew the default pools has not drawn: a session on a
# fresh machine takes a shift no session has used (the model card's lineage rows name the ones used).
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${DATA:-/work/data}
PY=${PY:-.venv/bin/python}
ROUNDS=${1:-40}
SHIFT=${SHIFT:-0}
A=$((201 + SHIFT)) B=$((206 + SHIFT)) C=$((213 + SHIFT)) D=$((214 + SHIFT))
S="$PY -m polycubenet.synth --n-cond 2048 --n-target 2048 --no-progress --workers 1"
mkdir -p "$DATA/mixs"
. scripts/link_shards.sh
link_shards "$DATA/mixf" "$DATA/mixs" ""  # MIXF's shards, where scripts/make_mixf.sh has written them
link() { link_shards "$DATA/$1" "$DATA/mixs" "$2"; }  # link SRC PREFIX: SRC's finished shards into $DATA/mixs
for r in $(seq 1 "$ROUNDS"); do
  n=$((256 * r))
  $S --out "$DATA/pool$A" --count $n --seed $A && link "pool$A" "p$A-"
  $S --out "$DATA/pool$B" --count $n --seed $B --cad-features --whole-slants && link "pool$B" "p$B-"
  if [ $((r % 3)) -eq 1 ]; then
    $S --out "$DATA/pool$D" --count $((256 * (r + 2) / 3)) --seed $D --turned 1.0 --bolt-circles 0.75 \
      --flanges 1.0 && link "pool$D" "p$D-"
  fi
  if [ $((r % 3)) -eq 0 ]; then
    $S --out "$DATA/pool$C" --count $((256 * r / 3)) --seed $C --turned 1.0 --bolt-circles 0.75 && link "pool$C" "p$C-"
  fi
  echo "round $r of $ROUNDS: $(ls "$DATA/mixs" | wc -l) shards in $DATA/mixs ($(date +%H:%M))"
done
