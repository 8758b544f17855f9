#!/usr/bin/env bash
# A one-node SLURM on this machine, loopback only, for trying hydra/launcher=slurm.
#
#   sudo scripts/slurm_one_node.sh start     # installs slurm-wlm + munge if absent (Debian)
#   export SLURM_CONF=/tmp/pipeline-slurm/slurm.conf
#   python -m pipeline -m experiment=smoke hydra/launcher=slurm \
#       hydra.launcher.cpus_per_task=1 hydra.launcher.mem_gb=2 seed=0,1
#   scripts/slurm_one_node.sh stop
#
# Needs root (munged's key, slurmd). Nothing is written under /etc/slurm: the daemons and
# every client (sbatch, squeue, submitit) read $SLURM_CONF. Processes are tracked without
# cgroups (proctrack/linuxproc), so it also runs in containers. State and logs live in
# $SLURM_DIR (default /tmp/pipeline-slurm); `status` prints sinfo and the daemons' logs.
set -euo pipefail

SLURM_DIR=${SLURM_DIR:-/tmp/pipeline-slurm}
CONF=$SLURM_DIR/slurm.conf
NODE=$(hostname -s)

install_packages() {
    if command -v slurmctld >/dev/null && command -v munged >/dev/null; then
        return
    fi
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge
}

start_munge() {
    install -d -o munge -g munge -m 0755 /run/munge
    install -d -o munge -g munge -m 0700 /var/lib/munge /var/log/munge
    if [ ! -s /etc/munge/munge.key ]; then
        install -d -o munge -g munge -m 0700 /etc/munge
        dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=128 status=none
        chown munge:munge /etc/munge/munge.key
        chmod 0400 /etc/munge/munge.key
    fi
    if ! munge -n >/dev/null 2>&1; then
        runuser -u munge -- /usr/sbin/munged
    fi
    munge -n | unmunge >/dev/null   # fails loudly if the credential round trip does not work
}

write_conf() {
    mkdir -p "$SLURM_DIR/state" "$SLURM_DIR/spool"
    local cpus mem_mb
    cpus=$(nproc)
    mem_mb=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024 ))
    cat > "$CONF" <<EOF
# Written by scripts/slurm_one_node.sh: one node, loopback only.
ClusterName=pipeline
SlurmctldHost=$NODE(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
ReturnToService=2
StateSaveLocation=$SLURM_DIR/state
SlurmdSpoolDir=$SLURM_DIR/spool
SlurmctldPidFile=$SLURM_DIR/slurmctld.pid
SlurmdPidFile=$SLURM_DIR/slurmd.pid
SlurmctldLogFile=$SLURM_DIR/slurmctld.log
SlurmdLogFile=$SLURM_DIR/slurmd.log
SlurmctldPort=6817
SlurmdPort=6818
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=local Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF
}

start() {
    install_packages
    start_munge
    write_conf
    export SLURM_CONF=$CONF
    pgrep -x slurmctld >/dev/null || slurmctld -c   # -c: a clean state, no old jobs
    pgrep -x slurmd >/dev/null || slurmd
    for _ in $(seq 60); do
        if sinfo -h -o %T 2>/dev/null | grep -qx idle; then
            sinfo
            echo "SLURM is up: export SLURM_CONF=$CONF"
            return
        fi
        sleep 1
    done
    echo "SLURM did not come up; logs in $SLURM_DIR:" >&2
    tail -n 20 "$SLURM_DIR"/slurm*.log >&2
    exit 1
}

stop() {
    pkill -x slurmd || true
    pkill -x slurmctld || true
}

case "${1:-}" in
    start) start ;;
    stop) stop ;;
    status) SLURM_CONF=$CONF sinfo; tail -n 5 "$SLURM_DIR"/slurm*.log ;;
    *) echo "usage: $0 start|stop|status" >&2; exit 2 ;;
esac
