#!/usr/bin/env bash
# A sweep through hydra/launcher=slurm on a one-node SLURM of this machine, then its check:
# the sweep's parent run and every child run FINISHED in one MLflow store.
#
#   sudo scripts/slurm_sweep.sh [RUNS_DIR] [extra Hydra overrides…]
#
# RUNS_DIR (default /tmp/pipeline-slurm-runs) is paths.runs: the SQLite store and the stage
# cache the SLURM tasks share (one machine here; a shared file system on a cluster).
# submitit polls `sacct`, which needs slurmdbd; without it every poll logs "Bypassing sacct
# error" and submitit reads each task's result file instead (harmless, just loud).
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-/tmp/pipeline-slurm-runs}
shift || true
PY=${PY:-.venv/bin/python}

scripts/slurm_one_node.sh start
export SLURM_CONF=${SLURM_DIR:-/tmp/pipeline-slurm}/slurm.conf
"$PY" -m pipeline -m experiment=smoke hydra/launcher=slurm \
    hydra.launcher.cpus_per_task=1 hydra.launcher.mem_gb=2 seed=0,1 \
    paths.runs="$RUNS" "$@"
"$PY" scripts/sweep_status.py --uri "sqlite:///$(realpath "$RUNS")/mlflow.db" --experiment smoke
