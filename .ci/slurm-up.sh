#!/usr/bin/env bash
# Starts a single-node Slurm cluster on this machine (for tests/slurm.rs): installs Debian's
# slurm-wlm and munge when missing, writes /etc/slurm/slurm.conf for the local host, starts
# munged, slurmctld and slurmd (as root, no systemd needed) and waits until `sinfo` shows the
# node idle. Idempotent: a cluster that already answers is left alone (unless the config
# changed); stopped daemons are restarted. Needs root. Exit code 1 with the reason when the
# cluster does not come up.
#
#   bash .ci/slurm-up.sh          bring it up (or check it is up)
#   bash .ci/slurm-up.sh --down   stop the daemons this script starts
set -euo pipefail

log() { echo "slurm-up: $*" >&2; }
die() {
    log "ERROR: $*"
    for f in /var/log/slurm/slurmctld.log /var/log/slurm/slurmd.log /var/log/munge/munged.log; do
        if [ -f "$f" ]; then
            log "--- last lines of $f"
            tail -n 20 "$f" >&2 || true
        fi
    done
    exit 1
}

stop_daemon() { # name
    local pids
    pids=$(pgrep -x "$1" || true)
    if [ -n "$pids" ]; then
        log "stopping $1 ($pids)"
        # shellcheck disable=SC2086
        kill $pids 2>/dev/null || true
        for _ in $(seq 50); do
            pgrep -x "$1" >/dev/null || return 0
            sleep 0.1
        done
        # shellcheck disable=SC2086
        kill -9 $pids 2>/dev/null || true
    fi
}

if [ "${1:-}" = "--down" ]; then
    stop_daemon slurmd
    stop_daemon slurmctld
    stop_daemon munged
    exit 0
fi

[ "$(id -u)" = 0 ] || die "must run as root (slurmctld and slurmd run as root here)"

# 1. Packages.
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
    || ! command -v munged >/dev/null || ! command -v sbatch >/dev/null; then
    log "installing slurm-wlm and munge (apt-get)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq || die "apt-get update failed"
    apt-get install -y -qq slurm-wlm munge >/dev/null || die "apt-get install slurm-wlm munge failed"
fi

host=$(hostname -s)
cpus=$(nproc)
mem_mb=$(awk '/MemTotal/ {print int($2 / 1024 * 0.8)}' /proc/meminfo)

# 2. Configuration (rewritten only when it differs, so a running cluster is not disturbed).
mkdir -p /etc/slurm /var/lib/slurm/slurmctld /var/lib/slurm/slurmd /var/log/slurm /run/slurm
conf=$(cat <<CONF
# Written by .ci/slurm-up.sh: a single-node test cluster on $host.
ClusterName=pipetest
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
SchedulerParameters=sched_interval=2
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
ReturnToService=2
MinJobAge=600
MaxArraySize=10001
KillWait=5
SlurmctldTimeout=30
SlurmdTimeout=30
InactiveLimit=0
Waittime=0
StateSaveLocation=/var/lib/slurm/slurmctld
SlurmdSpoolDir=/var/lib/slurm/slurmd
SlurmctldPidFile=/run/slurm/slurmctld.pid
SlurmdPidFile=/run/slurm/slurmd.pid
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
SlurmctldPort=6817
SlurmdPort=6818
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP OverSubscribe=NO
CONF
)
changed=0
if [ "$(cat /etc/slurm/slurm.conf 2>/dev/null || true)" != "$conf" ]; then
    printf '%s\n' "$conf" >/etc/slurm/slurm.conf
    changed=1
    log "wrote /etc/slurm/slurm.conf"
fi
if [ ! -f /etc/slurm/cgroup.conf ]; then
    # Not used by proctrack/linuxproc + task/none, but some slurmd builds read it at start.
    printf 'CgroupPlugin=autodetect\nIgnoreSystemd=yes\n' >/etc/slurm/cgroup.conf
fi

# 3. munge.
mkdir -p /etc/munge /run/munge /var/lib/munge /var/log/munge
if [ ! -s /etc/munge/munge.key ]; then
    log "creating /etc/munge/munge.key"
    if command -v mungekey >/dev/null; then
        mungekey --create --force --keyfile=/etc/munge/munge.key
    else
        dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none
    fi
fi
chown -R munge:munge /etc/munge /run/munge /var/lib/munge /var/log/munge
chmod 700 /etc/munge /var/lib/munge /var/log/munge
chmod 755 /run/munge
chmod 400 /etc/munge/munge.key
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    stop_daemon munged
    rm -f /run/munge/munged.pid /run/munge/munge.socket.2*
    log "starting munged"
    if command -v runuser >/dev/null; then
        runuser -u munge -- /usr/sbin/munged || die "munged did not start"
    else
        /usr/sbin/munged --force || die "munged did not start"
    fi
    for _ in $(seq 50); do
        munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break
        sleep 0.1
    done
    munge -n | unmunge >/dev/null 2>&1 || die "munge does not answer (munge -n | unmunge)"
fi

# 4. slurmctld and slurmd.
if [ "$changed" = 1 ]; then
    stop_daemon slurmd
    stop_daemon slurmctld
fi
if ! pgrep -x slurmctld >/dev/null; then
    log "starting slurmctld"
    /usr/sbin/slurmctld || die "slurmctld did not start"
fi
for _ in $(seq 100); do
    scontrol ping 2>/dev/null | grep -q "is UP" && break
    sleep 0.2
done
scontrol ping 2>/dev/null | grep -q "is UP" || die "slurmctld does not answer (scontrol ping)"
if ! pgrep -x slurmd >/dev/null; then
    log "starting slurmd"
    /usr/sbin/slurmd || die "slurmd did not start"
fi

# 5. Wait until the node is idle (or mixed/allocated: the cluster is up and working).
state=""
for _ in $(seq 150); do
    state=$(sinfo -h -n "$host" -o '%T' 2>/dev/null | head -n1 || true)
    case "$state" in
        idle | mixed | allocated | completing) break ;;
        down* | drain* | fail*)
            scontrol update NodeName="$host" State=RESUME 2>/dev/null || true ;;
    esac
    sleep 0.2
done
case "$state" in
    idle | mixed | allocated | completing) log "cluster up: node $host is $state ($cpus CPUs, ${mem_mb} MB)" ;;
    *) die "node $host did not become idle (sinfo says: '${state:-nothing}')" ;;
esac
