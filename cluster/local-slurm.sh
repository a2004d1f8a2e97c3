#!/usr/bin/env bash
# A single-node Slurm with accounting on this machine (Debian packages, no systemd), and a
# proof that the workflow runs on it through Snakemake's Slurm executor plugin with
# profiles/slurm: one Slurm job per rule instance (sacct), outputs byte-identical to a
# local run. docs/cluster.md tells the story and what a run printed.
#
#   cluster/local-slurm.sh install      packages, configs, daemons, account, plugin (idempotent)
#   cluster/local-slurm.sh run [quick|demo] [--rev COMMIT | --tree]   install, then the
#                                        workflow locally and on Slurm, and the two checks
#                                        (default: quick, HEAD's sources; --tree: the working tree)
#   cluster/local-slurm.sh status       sinfo, squeue and the daemons' pids
#   cluster/local-slurm.sh stop         stop the daemons this script started (pid files)
#
# Environment: CROSSLINE_SLURM_WORK (default /tmp/crossline-slurm) holds the working copies;
# CROSSLINE_SLURM_PARTITION / _ACCOUNT name the local cluster's partition and account (the
# defaults match profiles/slurm/config.yaml).
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
CLUSTER_NAME=crossline
PARTITION=${CROSSLINE_SLURM_PARTITION:-main}
ACCOUNT=${CROSSLINE_SLURM_ACCOUNT:-crossline}
WORK_ROOT=${CROSSLINE_SLURM_WORK:-/tmp/crossline-slurm}
ETC=/etc/slurm
RUN=/run/slurm
LOG=/var/log/slurm
LIB=/var/lib/slurm
HOST=$(hostname -s)

say() { printf '[local-slurm %(%H:%M:%S)T] %s\n' -1 "$*"; }
die() { say "ERROR: $*" >&2; exit 1; }

alive() { # pid file, process name -> true when that process runs (a stale file may name a reused pid)
    [[ -s $1 ]] && [[ $(cat "/proc/$(cat "$1")/comm" 2>/dev/null) == "$2" ]]
}

wait_for() { # seconds, description, command...
    local seconds=$1 what=$2; shift 2
    for ((i = 0; i < seconds * 2; i++)); do
        if "$@" >/dev/null 2>&1; then return 0; fi
        sleep 0.5
    done
    die "$what did not come up within ${seconds} s"
}

install_packages() {
    local need=()
    for p in munge mariadb-server slurmdbd slurmctld slurmd slurm-client; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed' || need+=("$p")
    done
    if ((${#need[@]})); then
        say "apt-get install ${need[*]}"
        # Keep the packages' init scripts from starting daemons during the install (there is
        # no init system here): a policy-rc.d of our own, removed after, unless one exists.
        local own_policy=0
        if [[ ! -e /usr/sbin/policy-rc.d ]]; then
            printf '#!/bin/sh\nexit 101\n' >/usr/sbin/policy-rc.d
            chmod 755 /usr/sbin/policy-rc.d
            own_policy=1
        fi
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" \
            >/tmp/local-slurm-apt.log 2>&1 || { tail -20 /tmp/local-slurm-apt.log; die "apt-get install failed"; }
        ((own_policy)) && rm -f /usr/sbin/policy-rc.d
    fi
    if ! python -c 'import snakemake_executor_plugin_slurm' 2>/dev/null; then
        say "pip install snakemake-executor-plugin-slurm"
        python -m pip install -q snakemake-executor-plugin-slurm
    fi
}

write_if_changed() { # path mode owner < content
    local path=$1 mode=$2 owner=$3 tmp
    tmp=$(mktemp)
    cat >"$tmp"
    if [[ -f $path ]] && cmp -s "$tmp" "$path"; then
        rm -f "$tmp"
    else
        install -m "$mode" -o "$owner" -g "$owner" "$tmp" "$path"
        rm -f "$tmp"
        say "wrote $path"
    fi
}

write_configs() {
    install -d -m 755 -o slurm -g slurm "$RUN" "$LOG" "$LIB" "$LIB/slurmctld" "$LIB/slurmd"
    local cpus mem_mb
    cpus=$(nproc)
    # all of MemTotal less 5 % for the system; slurmd drains a node that reports less than this
    mem_mb=$(awk '/^MemTotal:/ { printf "%d", $2 / 1024 * 0.95 }' /proc/meminfo)
    write_if_changed "$ETC/slurm.conf" 644 root <<EOF
# Written by cluster/local-slurm.sh: one node, this machine, $cpus CPUs, $mem_mb MB.
ClusterName=$CLUSTER_NAME
SlurmctldHost=$HOST
SlurmUser=slurm
AuthType=auth/munge
StateSaveLocation=$LIB/slurmctld
SlurmdSpoolDir=$LIB/slurmd
SlurmctldPidFile=$RUN/slurmctld.pid
SlurmdPidFile=$RUN/slurmd.pid
SlurmctldLogFile=$LOG/slurmctld.log
SlurmdLogFile=$LOG/slurmd.log
# No systemd and no writable cgroup tree in this container: processes are tracked through
# their parent pids and tasks are not bound; memory requests are scheduled, not enforced.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/linux
JobAcctGatherFrequency=10
# Accounting through slurmdbd, which the executor plugin's status queries (sacct) need; the
# comment (rule and wildcards) is stored, so sacct can show which rule instance a job was.
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
AccountingStorageEnforce=associations
AccountingStoreFlags=job_comment
JobCompType=jobcomp/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
MpiDefault=none
MailProg=/bin/true
ReturnToService=2
MinJobAge=300
KillWait=30
NodeName=$HOST CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=$PARTITION Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
    # Read by slurmd only when a cgroup plugin is configured (none is, above); written so
    # that nothing tries to mount or constrain a hierarchy this container does not let it.
    write_if_changed "$ETC/cgroup.conf" 644 root <<EOF
# Written by cluster/local-slurm.sh: cgroups unused (proctrack/linuxproc, task/none).
CgroupAutomount=no
ConstrainCores=no
ConstrainRAMSpace=no
ConstrainDevices=no
EOF
    local pass
    pass=$(sed -n 's/^StoragePass=//p' "$ETC/slurmdbd.conf" 2>/dev/null || true)
    [[ -n $pass ]] || pass=$(head -c 18 /dev/urandom | base64 | tr -dc 'A-Za-z0-9')
    write_if_changed "$ETC/slurmdbd.conf" 600 slurm <<EOF
# Written by cluster/local-slurm.sh.
AuthType=auth/munge
DbdHost=localhost
SlurmUser=slurm
LogFile=$LOG/slurmdbd.log
PidFile=$RUN/slurmdbd.pid
StorageType=accounting_storage/mysql
StorageHost=localhost
StorageUser=slurm
StoragePass=$pass
StorageLoc=slurm_acct_db
EOF
    DB_PASS=$pass
}

start_munge() {
    [[ -s /etc/munge/munge.key ]] || { mungekey --create 2>/dev/null || /usr/sbin/create-munge-key -f; }
    chown munge:munge /etc/munge/munge.key
    chmod 400 /etc/munge/munge.key
    install -d -m 755 -o munge -g munge /run/munge
    if ! alive /run/munge/munged.pid munged; then
        say "starting munged"
        runuser -u munge -- /usr/sbin/munged
    fi
    wait_for 20 munge bash -c 'munge -n | unmunge'
}

start_mariadb() {
    install -d -m 755 -o mysql -g mysql /run/mysqld
    if ! mariadb-admin --protocol=socket ping >/dev/null 2>&1; then
        say "starting mariadbd"
        setsid nohup /usr/sbin/mariadbd --user=mysql --pid-file=/run/mysqld/mysqld.pid \
            >>"$LOG/mariadb.log" 2>&1 </dev/null &
        wait_for 60 mariadb mariadb-admin --protocol=socket ping
    fi
    mariadb --protocol=socket <<EOF
CREATE DATABASE IF NOT EXISTS slurm_acct_db;
CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY '$DB_PASS';
ALTER USER 'slurm'@'localhost' IDENTIFIED BY '$DB_PASS';
GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';
EOF
}

start_slurm() {
    if ! alive "$RUN/slurmdbd.pid" slurmdbd; then
        say "starting slurmdbd"
        /usr/sbin/slurmdbd
    fi
    wait_for 60 slurmdbd sacctmgr -n show cluster
    if ! sacctmgr -nP show cluster format=cluster | grep -qx "$CLUSTER_NAME"; then
        sacctmgr -i add cluster "$CLUSTER_NAME" >/dev/null
    fi
    if ! sacctmgr -nP show account format=account | grep -qx "$ACCOUNT"; then
        sacctmgr -i add account "$ACCOUNT" Cluster="$CLUSTER_NAME" \
            Description="crossline workflow" Organization=crossline >/dev/null
    fi
    if ! sacctmgr -nP show assoc where user=root account="$ACCOUNT" format=user | grep -qx root; then
        sacctmgr -i add user root Account="$ACCOUNT" DefaultAccount="$ACCOUNT" >/dev/null
    fi
    if alive "$RUN/slurmctld.pid" slurmctld && [[ $ETC/slurm.conf -nt $RUN/slurmctld.pid ]]; then
        say "slurm.conf changed: scontrol reconfigure"
        scontrol reconfigure
        touch "$RUN/slurmctld.pid"
    fi
    if ! alive "$RUN/slurmctld.pid" slurmctld; then
        say "starting slurmctld"
        /usr/sbin/slurmctld
    fi
    wait_for 60 slurmctld scontrol ping
    if ! alive "$RUN/slurmd.pid" slurmd; then
        say "starting slurmd"
        /usr/sbin/slurmd
    fi
    local state
    for ((i = 0; i < 120; i++)); do
        state=$(sinfo -h -n "$HOST" -o %T 2>/dev/null | head -1)
        [[ $state == idle || $state == mixed || $state == allocated ]] && break
        if [[ $state == down* || $state == drain* ]]; then
            scontrol update nodename="$HOST" state=resume 2>/dev/null || true
        fi
        sleep 0.5
    done
    [[ $state == idle || $state == mixed || $state == allocated ]] ||
        die "node $HOST is '$state', not idle (see $LOG/slurmd.log, $LOG/slurmctld.log)"
    say "cluster $CLUSTER_NAME up: partition $PARTITION, account $ACCOUNT, node $HOST $state"
}

cmd_install() {
    [[ $(id -u) == 0 ]] || die "run as root (installs packages and starts daemons)"
    local t0=$SECONDS
    install_packages
    write_configs
    start_munge
    start_mariadb
    start_slurm
    sinfo
    say "install done in $((SECONDS - t0)) s"
}

cmd_status() {
    sinfo || true
    squeue || true
    for d in munge/munged mysqld/mariadbd slurm/slurmdbd slurm/slurmctld slurm/slurmd; do
        local f=/run/${d%/*}/${d#*/}.pid
        [[ $d == mysqld/* ]] && f=/run/mysqld/mysqld.pid
        if alive "$f" "${d#*/}"; then echo "${d#*/}: pid $(cat "$f")"; else echo "${d#*/}: not running"; fi
    done
}

cmd_stop() {
    for d in slurmd slurmctld slurmdbd; do
        if alive "$RUN/$d.pid" "$d"; then say "stopping $d"; kill "$(cat "$RUN/$d.pid")"; fi
    done
    mariadb-admin --protocol=socket shutdown 2>/dev/null && say "stopped mariadbd" || true
    if alive /run/munge/munged.pid munged; then say "stopping munged"; kill "$(cat /run/munge/munged.pid)"; fi
}

case ${1:-install} in
    install) cmd_install ;;
    run) shift; cmd_install; exec python "$REPO/cluster/prove.py" "${@:-quick}" ;;
    status) cmd_status ;;
    stop) cmd_stop ;;
    *) sed -n '2,16p' "$0"; exit 2 ;;
esac
