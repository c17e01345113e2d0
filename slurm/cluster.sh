#!/usr/bin/env bash
# A real single-node SLURM cluster on this machine, for tests and trying the profile:
# Debian's slurm-wlm + munge, with slurmdbd on a private MariaDB so that `sacct` works.
#
#   slurm/cluster.sh up       install if needed, start everything, wait until the node is idle
#   slurm/cluster.sh down     stop what `up` started (only those processes), keep the state dir
#   slurm/cluster.sh status   what runs
#   slurm/cluster.sh purge    down, then delete the state dir
#
# Idempotent: `up` on a running cluster does nothing. Needs root (apt-get, daemons).
# PID 1 is not systemd here, so the daemons are started directly; slurm runs as root with
# proctrack/linuxproc and task/none. State, configs, logs and PID files live in $PSD_SLURM_DIR.
#
# The node declares PSD_SLURM_GPUS (default 2) GPUs as a generic resource (gres/gpu) whether or
# not the machine has any, so that jobs asking for a GPU (the profile's train, evaluate and
# benchmark: --gpus=1) are accepted, queued at most one per declared GPU, accounted (sacct's
# AllocTRES shows gres/gpu=1) and run. Slurm 22.05 drops a GPU without a device file from the
# node's count ("Removing file-less GPU"), so each stands in as $PSD_SLURM_DIR/dev/gpuN, a
# symlink to /dev/null: a character device that Slurm accepts and nothing opens. No CUDA device
# appears in the jobs unless the machine has one; psdfactory's device `auto` then runs on the
# CPU and says so in the job's log.
set -euo pipefail

STATE=${PSD_SLURM_DIR:-/var/tmp/psdfactory-slurm}
CLUSTER=psdlocal
PARTITION=${PSD_SLURM_PARTITION:-local}
ACCOUNT=${PSD_SLURM_ACCOUNT:-psdfactory}
DB_PORT=${PSD_SLURM_DB_PORT:-33061}
CTLD_PORT=${PSD_SLURM_CTLD_PORT:-6817}
SLURMD_PORT=${PSD_SLURM_SLURMD_PORT:-6818}
DBD_PORT=${PSD_SLURM_DBD_PORT:-6819}
GPUS=${PSD_SLURM_GPUS:-2}
HOST=$(hostname -s)
CONF=$STATE/etc/slurm.conf
export SLURM_CONF=$CONF

log() { printf '[slurm/cluster.sh] %s\n' "$*" >&2; }

install_packages() {
    local missing=()
    for cmd in slurmctld slurmd slurmdbd munged mariadbd sbatch sacct; do
        command -v "$cmd" >/dev/null 2>&1 || missing+=("$cmd")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    log "installing slurm-wlm, slurmdbd, munge, mariadb-server (missing: ${missing[*]})"
    # keep the packages' init scripts from starting system-wide daemons
    local policy=/usr/sbin/policy-rc.d created=0
    if [ ! -e $policy ]; then printf '#!/bin/sh\nexit 101\n' > $policy; chmod +x $policy; created=1; fi
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        slurm-wlm slurmdbd slurm-client munge mariadb-server mariadb-client >/dev/null
    [ $created -eq 1 ] && rm -f $policy
    return 0
}

alive() { [ -f "$STATE/run/$1.pid" ] && kill -0 "$(cat "$STATE/run/$1.pid")" 2>/dev/null; }

wait_for() {  # wait_for SECONDS DESCRIPTION COMMAND...
    local secs=$1 what=$2; shift 2
    for _ in $(seq 1 $((secs * 5))); do "$@" >/dev/null 2>&1 && return 0; sleep 0.2; done
    log "timed out after ${secs}s waiting for $what; logs in $STATE/log"
    return 1
}

write_configs() {
    if ! [[ $GPUS =~ ^[1-9][0-9]?$ ]]; then log "PSD_SLURM_GPUS must be a whole number from 1 to 99, not '$GPUS'"; exit 2; fi
    mkdir -p "$STATE"/{etc,run,log,spool/ctld,spool/d,munge,db}
    local cpus mem
    cpus=$(nproc)
    mem=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024 ))
    cat > "$CONF" <<CONF
ClusterName=$CLUSTER
SlurmctldHost=$HOST
SlurmUser=root
SlurmdUser=root
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
AuthType=auth/munge
CryptoType=crypto/munge
StateSaveLocation=$STATE/spool/ctld
SlurmdSpoolDir=$STATE/spool/d
SlurmctldPidFile=$STATE/run/slurmctld.pid
SlurmdPidFile=$STATE/run/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SwitchType=switch/none
MpiDefault=none
ReturnToService=2
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStoragePort=$DBD_PORT
AccountingStorageEnforce=associations
AccountingStorageTRES=gres/gpu
JobCompType=jobcomp/none
MinJobAge=300
KillWait=5
InactiveLimit=0
SlurmctldTimeout=30
SlurmdTimeout=30
GresTypes=gpu
NodeName=$HOST CPUs=$cpus RealMemory=$mem Gres=gpu:$GPUS State=UNKNOWN
PartitionName=$PARTITION Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
CONF
    # slurmd reads gres.conf beside slurm.conf; AutoDetect=off: no probing for real GPUs (NVML)
    rm -rf "$STATE/dev" && mkdir -p "$STATE/dev"
    printf 'AutoDetect=off\n' > "$STATE/etc/gres.conf"
    for i in $(seq 0 $((GPUS - 1))); do
        ln -s /dev/null "$STATE/dev/gpu$i"
        printf 'NodeName=%s Name=gpu File=%s\n' "$HOST" "$STATE/dev/gpu$i" >> "$STATE/etc/gres.conf"
    done
    cat > "$STATE/etc/slurmdbd.conf" <<CONF
AuthType=auth/munge
DbdHost=localhost
DbdPort=$DBD_PORT
SlurmUser=root
PidFile=$STATE/run/slurmdbd.pid
LogFile=$STATE/log/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=$DB_PORT
StorageUser=slurm
StoragePass=psdfactory
StorageLoc=slurm_acct_db
CONF
    chmod 600 "$STATE/etc/slurmdbd.conf"
}

MUNGE_SOCKET_PATH=/run/munge/munge.socket.2  # where Slurm's clients look for munge

start_munge() {
    alive munged && return 0
    if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
        log "using the munged already running at $MUNGE_SOCKET_PATH"
        return 0
    fi
    if [ ! -f "$STATE/munge/munge.key" ]; then
        dd if=/dev/urandom bs=1 count=1024 of="$STATE/munge/munge.key" status=none
        chmod 400 "$STATE/munge/munge.key"
    fi
    chmod 700 "$STATE/munge"
    mkdir -p "$(dirname $MUNGE_SOCKET_PATH)"
    munged --force --key-file "$STATE/munge/munge.key" --socket "$MUNGE_SOCKET_PATH" \
        --pid-file "$STATE/run/munged.pid" --log-file "$STATE/log/munged.log" --seed-file "$STATE/munge/munge.seed"
    wait_for 10 munged bash -c "munge -n | unmunge"
}

start_mariadb() {
    alive mariadbd && return 0
    if [ ! -d "$STATE/db/mysql" ]; then
        mariadb-install-db --user=root --datadir="$STATE/db" --auth-root-authentication-method=normal >"$STATE/log/mariadb-install.log" 2>&1
    fi
    mariadbd --user=root --datadir="$STATE/db" --socket="$STATE/run/mysqld.sock" --pid-file="$STATE/run/mariadbd.pid" \
        --port="$DB_PORT" --bind-address=127.0.0.1 --skip-name-resolve --log-error="$STATE/log/mariadb.log" \
        --innodb-buffer-pool-size=64M >/dev/null 2>&1 &
    wait_for 60 "MariaDB" mariadb --socket="$STATE/run/mysqld.sock" -uroot -e "SELECT 1"
    mariadb --socket="$STATE/run/mysqld.sock" -uroot <<SQL
CREATE DATABASE IF NOT EXISTS slurm_acct_db;
CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY 'psdfactory';
CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY 'psdfactory';
GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';
GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';
FLUSH PRIVILEGES;
SQL
}

start_slurm() {
    if ! alive slurmdbd; then
        slurmdbd  # reads slurmdbd.conf beside $SLURM_CONF
        wait_for 60 slurmdbd sacctmgr -i list cluster
    fi
    sacctmgr -i add cluster "$CLUSTER" >/dev/null 2>&1 || true
    sacctmgr -i add account "$ACCOUNT" Cluster="$CLUSTER" Description=psdfactory Organization=psdfactory >/dev/null 2>&1 || true
    sacctmgr -i add user root Account="$ACCOUNT" Cluster="$CLUSTER" >/dev/null 2>&1 || true
    if ! alive slurmctld; then
        slurmctld -f "$CONF"
        wait_for 30 slurmctld scontrol ping
    fi
    if ! alive slurmd; then
        slurmd -f "$CONF" || { log "slurmd did not start (a bad gres.conf?); see $STATE/log/slurmd.log"; return 1; }
        # slurmd returns before it writes its PID file: wait for the node to report in
    fi
    wait_for 60 "node $HOST to be idle" bash -c "sinfo -h -N -o %T | grep -qE '^(idle|mixed|allocated)'"
    scontrol update NodeName="$HOST" State=RESUME >/dev/null 2>&1 || true
}

stop_one() {
    local name=$1
    if alive "$name"; then
        local pid; pid=$(cat "$STATE/run/$name.pid")
        kill "$pid" 2>/dev/null || true
        for _ in $(seq 1 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
        kill -9 "$pid" 2>/dev/null || true
        log "stopped $name ($pid)"
    fi
    rm -f "$STATE/run/$name.pid"
}

link_default_conf() {
    # Job steps (srun inside a job) look for /etc/slurm/slurm.conf when SLURM_CONF does not reach
    # them: point it at this cluster's config, unless the machine has a config of its own.
    mkdir -p /etc/slurm
    if [ ! -e /etc/slurm/slurm.conf ] || [ "$(readlink /etc/slurm/slurm.conf)" = "$CONF" ]; then
        ln -sfn "$CONF" /etc/slurm/slurm.conf
    else
        log "/etc/slurm/slurm.conf exists and is not ours: left alone (export SLURM_CONF=$CONF)"
    fi
}

unlink_default_conf() {
    if [ "$(readlink /etc/slurm/slurm.conf 2>/dev/null)" = "$CONF" ]; then rm -f /etc/slurm/slurm.conf; fi
}

case "${1:-}" in
    up)
        install_packages
        # the configs follow PSD_SLURM_*_PORT: written anew whenever no daemon of this state folder
        # runs (a running cluster keeps the ports it was started with)
        if [ ! -f "$CONF" ] || ! { alive slurmctld || alive slurmdbd || alive mariadbd; }; then write_configs; fi
        link_default_conf
        start_munge
        start_mariadb
        start_slurm
        log "up: cluster $CLUSTER, partition $PARTITION, account $ACCOUNT; before using it: export SLURM_CONF=$CONF"
        ;;
    down)
        for d in slurmd slurmctld slurmdbd mariadbd munged; do stop_one "$d"; done
        unlink_default_conf
        ;;
    purge)
        "$0" down
        rm -rf "$STATE"
        ;;
    status)
        for d in munged mariadbd slurmdbd slurmctld slurmd; do
            if alive "$d"; then echo "$d: running ($(cat "$STATE/run/$d.pid"))"; else echo "$d: stopped"; fi
        done
        if alive slurmctld; then sinfo; fi
        ;;
    env)
        echo "export SLURM_CONF=$CONF"
        ;;
    *)
        echo "usage: $0 up|down|status|purge|env" >&2
        exit 2
        ;;
esac
