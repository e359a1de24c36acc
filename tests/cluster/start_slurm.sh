#!/usr/bin/env bash
# A real one-node SLURM cluster on localhost, for tests/test_slurm.py (make cluster-test)
# and for trying profiles/slurm by hand. Debian/Ubuntu packages slurm-wlm + munge, no
# slurmdbd (no accounting), no systemd: the daemons are started directly.
#
#   tests/cluster/start_slurm.sh [start]   install if missing (root + apt-get), start, wait
#                                          until the node is idle; a running cluster is reused
#   tests/cluster/start_slurm.sh stop      stop slurmd and slurmctld (and munged if started here)
#   tests/cluster/start_slurm.sh status    exit 0 when the node answers and is idle
#
# The configuration goes to /etc/slurm/slurm.conf, where every client (and srun inside a
# job) looks: snakemake's slurm-jobstep plugin drops SLURM_* variables, SLURM_CONF too,
# before its srun, so a configuration elsewhere is not found inside the jobs. An existing
# /etc/slurm/slurm.conf that this script did not write is left alone (exit 3). Logs, pid
# files and state live in $RESCU_SLURM_DIR (default /tmp/rescu-slurm). `start` prints
#   export SLURM_CONF=/etc/slurm/slurm.conf
# Exit status: 0 running, 3 SLURM cannot be had here (not root, no apt-get, install or
# daemons failed: the message says which), 2 usage.
set -u

DIR=${RESCU_SLURM_DIR:-/tmp/rescu-slurm}
CONF=${RESCU_SLURM_CONF:-/etc/slurm/slurm.conf}
MARK="# written by tests/cluster/start_slurm.sh"
PARTITION=${RESCU_SLURM_PARTITION:-main}
CTLD_PORT=${RESCU_SLURMCTLD_PORT:-6817}
SLURMD_PORT=${RESCU_SLURMD_PORT:-6818}
WAIT_S=${RESCU_SLURM_WAIT_S:-60}
export SLURM_CONF=$CONF
PATH=$PATH:/usr/sbin:/sbin

say() { echo "start_slurm: $*" >&2; }
cannot() { say "$*"; exit 3; }
alive() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }
node_state() { sinfo -h -N -n localhost -o '%T' 2>/dev/null | head -1; }
is_root() { [ "$(id -u)" = 0 ]; }

install_if_missing() {
    command -v slurmctld >/dev/null && command -v slurmd >/dev/null \
        && command -v munged >/dev/null && command -v sbatch >/dev/null && return 0
    is_root || cannot "slurm-wlm/munge not installed and not root: cannot install them"
    command -v apt-get >/dev/null || cannot "slurm-wlm/munge not installed and no apt-get"
    say "installing slurm-wlm munge (apt-get)"
    export DEBIAN_FRONTEND=noninteractive
    if ! apt-get install -y -q --no-install-recommends slurm-wlm munge >"$DIR/apt.log" 2>&1; then
        apt-get update -q >>"$DIR/apt.log" 2>&1
        apt-get install -y -q --no-install-recommends slurm-wlm munge >>"$DIR/apt.log" 2>&1 \
            || cannot "apt-get install slurm-wlm munge failed (see $DIR/apt.log)"
    fi
}

start_munge() {
    # a munged that already answers (the system's own) is used as it is
    if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then return 0; fi
    local key=/etc/munge/munge.key
    if [ ! -s "$key" ]; then
        mkdir -p /etc/munge
        if command -v mungekey >/dev/null; then mungekey --create --keyfile="$key" --force
        else dd if=/dev/urandom of="$key" bs=1 count=1024 status=none; fi
    fi
    local user=root
    id munge >/dev/null 2>&1 && user=munge
    mkdir -p /run/munge /var/lib/munge /var/log/munge
    chown "$user" "$key" /run/munge /var/lib/munge /var/log/munge
    chmod 0400 "$key"; chmod 0755 /run/munge; chmod 0700 /var/lib/munge /var/log/munge
    if [ "$user" = root ]; then munged --force
    else runuser -u munge -- munged --force 2>/dev/null || su -s /bin/sh munge -c "munged --force"; fi
    touch "$DIR/munged.started-here"
    for _ in $(seq 20); do
        munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && return 0
        sleep 0.5
    done
    cannot "munged does not answer (see /var/log/munge/munged.log)"
}

write_conf() {
    # the node as slurmd sees it (CPUs, sockets, cores, threads, RealMemory), named localhost
    local node
    node=$(slurmd -C 2>/dev/null | grep '^NodeName=' | sed -E 's/^NodeName=[^ ]+/NodeName=localhost/; s/ UpTime=.*//')
    [ -n "$node" ] || cannot "slurmd -C does not describe this machine"
    if [ -e "$CONF" ] && ! grep -qF "$MARK" "$CONF"; then
        cannot "$CONF exists and was not written by this script: not replaced"
    fi
    mkdir -p "$DIR/state" "$DIR/spool" "$(dirname "$CONF")"
    cat >"$CONF.new" <<EOF
$MARK: one node (this machine), one default partition,
# no accounting (no slurmdbd; sacct has nothing to show: use slurm-status-command squeue)
ClusterName=rescu
SlurmctldHost=localhost
SlurmUser=root
SlurmdUser=root
SlurmctldPort=$CTLD_PORT
SlurmdPort=$SLURMD_PORT
AuthType=auth/munge
CredType=cred/munge
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
ReturnToService=2
MinJobAge=300
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
StateSaveLocation=$DIR/state
SlurmdSpoolDir=$DIR/spool
SlurmctldPidFile=$DIR/slurmctld.pid
SlurmdPidFile=$DIR/slurmd.pid
SlurmctldLogFile=$DIR/slurmctld.log
SlurmdLogFile=$DIR/slurmd.log
$node NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=$PARTITION Nodes=localhost Default=YES MaxTime=INFINITE State=UP
EOF
    mv "$CONF.new" "$CONF"
}

wait_idle() {
    local state
    for _ in $(seq "$WAIT_S"); do
        state=$(node_state)
        case "$state" in
            idle|mixed|allocated|completing) return 0 ;;
            down*|drain*|drained*|fail*)
                scontrol update nodename=localhost state=resume >/dev/null 2>&1 ;;
        esac
        sleep 1
    done
    cannot "node not idle after ${WAIT_S}s (state '${state:-no answer}'; see $DIR/slurmctld.log, $DIR/slurmd.log)"
}

start() {
    mkdir -p "$DIR" || cannot "cannot create $DIR"
    if grep -qsF "$MARK" "$CONF" && alive "$DIR/slurmctld.pid" && alive "$DIR/slurmd.pid"; then
        wait_idle
        say "already running (node $(node_state))"
        echo "export SLURM_CONF=$CONF"
        return 0
    fi
    is_root || cannot "not root: cannot start slurmctld/slurmd"
    install_if_missing
    start_munge
    write_conf
    alive "$DIR/slurmctld.pid" || slurmctld -f "$CONF" \
        || cannot "slurmctld did not start (see $DIR/slurmctld.log)"
    alive "$DIR/slurmd.pid" || slurmd -f "$CONF" -N localhost \
        || cannot "slurmd did not start (see $DIR/slurmd.log)"
    wait_idle
    say "running: partition $PARTITION, node $(sinfo -h -N -o '%N %c CPUs %m MB' | head -1)"
    echo "export SLURM_CONF=$CONF"
}

stop() {
    local f pid
    for f in slurmd slurmctld; do
        if alive "$DIR/$f.pid"; then
            pid=$(cat "$DIR/$f.pid")
            kill "$pid"
            for _ in $(seq 20); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
        fi
        rm -f "$DIR/$f.pid"
    done
    if [ -e "$DIR/munged.started-here" ] && [ -s /run/munge/munged.pid ]; then
        kill "$(cat /run/munge/munged.pid)" 2>/dev/null
        rm -f "$DIR/munged.started-here"
    fi
    say "stopped"
}

case "${1:-start}" in
    start) start ;;
    stop) stop ;;
    status)
        grep -qsF "$MARK" "$CONF" || exit 3
        case "$(node_state)" in idle|mixed|allocated|completing) echo "export SLURM_CONF=$CONF" ;; *) exit 3 ;; esac ;;
    *) echo "usage: $0 [start|stop|status]" >&2; exit 2 ;;
esac
