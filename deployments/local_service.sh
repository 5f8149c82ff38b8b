#!/usr/bin/env bash
# The service of deployments/README.md on one machine, for real: PostgreSQL, the Prefect server on it, the
# deployments of deployments/prefect.yaml, a process worker on the cpu-pool, and one triggered drop scan
# whose flow run is read back from the server's API and whose parts end up meshed.
#
#   deployments/local_service.sh [WORKDIR]          (default /tmp/polycubenet-service; run `make setup` first)
#
# What it does, each step as the README says for a site:
#   1. PostgreSQL: the distribution's server (apt-get install postgresql when it is missing), a fresh
#      cluster in WORKDIR/pg on port $PGPORT (default 55432), database "prefect";
#   2. `prefect server start` with PREFECT_API_DATABASE_CONNECTION_URL=postgresql+asyncpg://... on $API_PORT;
#   3. work pool cpu-pool (type process); `prefect deploy` of the nightly-scan deployment from
#      deployments/prefect.yaml, with the site paths edited for this machine (the repository as the working
#      directory, WORKDIR/drop and WORKDIR/meshes, a local Dask cluster) -- what the yaml says to edit per site;
#   4. a `prefect worker start --pool cpu-pool`;
#   5. two example parts copied into the drop folder, `prefect deployment run scan-drops/nightly-scan --watch`;
#   6. the run's state from the API (`prefect flow-run inspect`) and the manifest's rows; exit 0 only when
#      the run Completed and every dropped part is meshed.
# Everything it started is stopped at the end (the database files stay in WORKDIR).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
W=${1:-/tmp/polycubenet-service}
PGPORT=${PGPORT:-55432}
API_PORT=${API_PORT:-4299}
BIN=$ROOT/.venv/bin
[ -x "$BIN/prefect" ] || { echo "no $BIN/prefect: run make setup first" >&2; exit 2; }
rm -rf "$W" && mkdir -p "$W"/{drop,meshes,pg,prefect-home}
PIDS=()
cleanup() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  [ -n "${PG_CTL:-}" ] && as_pg "$PG_CTL" -D "$W/pg/data" -m fast stop >/dev/null 2>&1 || true
}
trap cleanup EXIT

# --- 1. PostgreSQL ---------------------------------------------------------------------------------------
if ! ls -d /usr/lib/postgresql/*/bin >/dev/null 2>&1; then
  sudo_cmd=""; [ "$(id -u)" = 0 ] || sudo_cmd=sudo
  $sudo_cmd apt-get install -y --no-install-recommends postgresql
fi
PGBIN=$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -1)
PG_CTL=$PGBIN/pg_ctl
if [ "$(id -u)" = 0 ]; then  # the server refuses to run as root: run it as the postgres user
  chown -R postgres "$W/pg"
  as_pg() { runuser -u postgres -- "$@"; }
else
  as_pg() { "$@"; }
fi
as_pg "$PGBIN/initdb" -D "$W/pg/data" -U prefect --auth=trust >/dev/null
as_pg "$PG_CTL" -D "$W/pg/data" -o "-p $PGPORT -k $W/pg -c listen_addresses=127.0.0.1" -l "$W/pg/log" -w start >/dev/null
as_pg "$PGBIN/createdb" -h 127.0.0.1 -p "$PGPORT" -U prefect prefect
echo "[1] PostgreSQL $("$PGBIN/postgres" --version | awk '{print $3}') on 127.0.0.1:$PGPORT, database prefect"

# --- 2. Prefect server on it ------------------------------------------------------------------------------
export PREFECT_HOME=$W/prefect-home
export PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1
PREFECT_API_DATABASE_CONNECTION_URL="postgresql+asyncpg://prefect@127.0.0.1:$PGPORT/prefect" \
  "$BIN/prefect" server start --host 127.0.0.1 --port "$API_PORT" > "$W/server.log" 2>&1 &
PIDS+=($!)
export PREFECT_API_URL=http://127.0.0.1:$API_PORT/api
for _ in $(seq 120); do
  curl -sf "$PREFECT_API_URL/health" >/dev/null && break
  sleep 1
done
curl -sf "$PREFECT_API_URL/health" >/dev/null || { echo "the Prefect server did not start: $W/server.log" >&2; exit 1; }
echo "[2] Prefect server $PREFECT_API_URL on PostgreSQL ($(grep -c . "$W/server.log") log lines)"

# --- 3. work pool and deployment -------------------------------------------------------------------------
"$BIN/prefect" work-pool create cpu-pool --type process >/dev/null
sed -e "s#directory: /opt/polycubenet#directory: $ROOT#" \
    -e "s#/shared/polycubenet/drop#$W/drop#" -e "s#/shared/polycubenet/meshes#$W/meshes#" \
    -e "s#dask_address: tcp://dask-scheduler:8786#dask_address: null#" \
    deployments/prefect.yaml > "$W/prefect.yaml"
"$BIN/prefect" --no-prompt deploy --prefect-file "$W/prefect.yaml" --name nightly-scan > "$W/deploy.log" 2>&1 \
  || { cat "$W/deploy.log" >&2; exit 1; }
echo "[3] deployed scan-drops/nightly-scan to cpu-pool"

# --- 4. a worker ------------------------------------------------------------------------------------------
PATH=$BIN:$PATH "$BIN/prefect" worker start --pool cpu-pool --type process > "$W/worker.log" 2>&1 &
PIDS+=($!)
echo "[4] process worker on cpu-pool (log $W/worker.log)"

# --- 5. drop two parts, trigger the scan -----------------------------------------------------------------
cp examples/parts/l_block.stl examples/parts/u_channel.stl "$W/drop/"
"$BIN/prefect" deployment run scan-drops/nightly-scan -p polycube='"classical"' -p target_hexes=1500 \
  --watch --watch-timeout 1200 > "$W/run.log" 2>&1 || true
RUN_ID=$(grep -oE "UUID: [0-9a-f-]{36}" "$W/run.log" | head -1 | awk '{print $2}')
[ -n "$RUN_ID" ] || { cat "$W/run.log" >&2; exit 1; }

# --- 6. what the API and the manifest say ----------------------------------------------------------------
STATE=$(curl -sf "$PREFECT_API_URL/flow_runs/$RUN_ID" | "$BIN/python" -c "import json,sys; print(json.load(sys.stdin)['state']['type'])")
echo "[5] flow run $RUN_ID: $STATE (from $PREFECT_API_URL/flow_runs/$RUN_ID)"
"$BIN/python" - "$W/meshes/manifest.json" <<'EOF'
import json, sys
rows = json.load(open(sys.argv[1]))["parts"]
for r in rows:
    q = r.get("quality") or {}
    print(f"    {r['name']:<12} {r['status']:<7} valid={q.get('valid')} sj_min={q.get('sj_min')} hexes={q.get('hexes')}")
ok = len(rows) == 2 and all(r["status"] == "meshed" for r in rows)
print("[6] manifest: " + ("both dropped parts meshed" if ok else "NOT all parts meshed"))
sys.exit(0 if ok else 1)
EOF
[ "$STATE" = COMPLETED ]
