#!/usr/bin/env bash
# A sweep whose jobs log to an `mlflow server` on 127.0.0.1 (MLFLOW_TRACKING_URI) instead
# of a SQLite file, then its check: the parent run and every child FINISHED on the server.
#
#   scripts/tracking_server_sweep.sh [WORK_DIR] [extra Hydra overrides…]
#
# WORK_DIR (default /tmp/pipeline-server) holds the server's store (server.db), its
# artifacts (served through the server: mlflow-artifacts:/) and paths.runs (the cache).
# The server is stopped at the end; PORT (default 5055) picks its port.
set -euo pipefail
cd "$(dirname "$0")/.."
WORK=$(realpath -m "${1:-/tmp/pipeline-server}")
shift || true
PY=${PY:-.venv/bin/python}
PORT=${PORT:-5055}
mkdir -p "$WORK"

"$PY" -m mlflow server --host 127.0.0.1 --port "$PORT" --workers 1 \
    --backend-store-uri "sqlite:///$WORK/server.db" \
    --artifacts-destination "$WORK/server-artifacts" > "$WORK/server.log" 2>&1 &
SERVER=$!
trap 'kill $SERVER 2>/dev/null; wait $SERVER 2>/dev/null || true' EXIT
export MLFLOW_TRACKING_URI=http://127.0.0.1:$PORT
for _ in $(seq 120); do
    curl -sf "$MLFLOW_TRACKING_URI/health" >/dev/null && break
    kill -0 $SERVER 2>/dev/null || { tail -n 20 "$WORK/server.log" >&2; exit 1; }
    sleep 1
done

"$PY" -m pipeline -m experiment=smoke hydra/launcher=local seed=0,1 paths.runs="$WORK/runs" "$@"
"$PY" scripts/sweep_status.py --uri "$MLFLOW_TRACKING_URI" --experiment smoke
