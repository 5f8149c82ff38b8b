# Sourced by scripts/make_mixf.sh and scripts/grow_pool.sh.
# link_shards SRC DEST PREFIX: every finished shard of folder SRC linked into folder DEST as shard-PREFIX<n>.npz
# (a shard already linked is left as it is), so a run reading DEST with --reload-every picks it up.
link_shards() {
  for f in "$1"/shard-*.npz; do
    [ -e "$f" ] || continue
    b=$(basename "$f")
    [ -e "$2/shard-$3${b#shard-}" ] || ln -s "$f" "$2/shard-$3${b#shard-}"
  done
}
