#!/usr/bin/env bash
# Start a private single-node Slurm cluster (munged, slurmctld, slurmd) whose
# every file lives in DIR; clients reach it with SLURM_CONF=DIR/slurm.conf.
# Exit 0 when `sinfo` shows the node idle; exit 2 with one line on stderr
# saying why when it cannot be had (not installed, not root, a daemon does
# not start). `teardown.sh DIR` stops what this started.
# Usage: setup.sh DIR
set -u
dir=${1:?usage: setup.sh DIR}
skip() { echo "slurm unavailable: $*" >&2; exit 2; }

for cmd in munged slurmctld slurmd sbatch sinfo; do
  command -v "$cmd" >/dev/null 2>&1 || skip "$cmd not installed (apt-get install slurm-wlm munge)"
done
[ "$(id -u)" = 0 ] || skip "the daemons need root"

mkdir -p "$dir/state" "$dir/spool" "$dir/munge"
chmod 700 "$dir" "$dir/munge"
dir=$(cd "$dir" && pwd)

# munge: its own key, socket and pid file (a system munged, if any, is left alone).
key="$dir/munge/munge.key"
head -c 1024 /dev/urandom > "$key" && chmod 400 "$key"
socket="$dir/munge/munge.sock"
munged --force --key-file="$key" --socket="$socket" --pid-file="$dir/munge/munged.pid" \
  --log-file="$dir/munge/munged.log" --seed-file="$dir/munge/munged.seed" \
  || skip "munged did not start: $(tail -n 3 "$dir/munge/munged.log" 2>/dev/null)"

# Free-looking ports, so that a system Slurm on the defaults is not disturbed.
base=$((20000 + RANDOM % 20000))
cpus=$(nproc)
mem=$(awk '/MemTotal/ {print int($2 / 1024 * 0.8)}' /proc/meminfo)
host=$(hostname -s)
cat > "$dir/slurm.conf" <<CONF
ClusterName=nerflabeltest
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$socket
SlurmctldPort=$base
SlurmdPort=$((base + 1))
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
KillWait=10
MaxArraySize=10001
NodeName=localhost NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=debug Nodes=localhost Default=YES MaxTime=INFINITE State=UP
CONF
export SLURM_CONF="$dir/slurm.conf"

slurmctld -f "$SLURM_CONF" -c || skip "slurmctld did not start: $(tail -n 3 "$dir/slurmctld.log" 2>/dev/null)"
slurmd -f "$SLURM_CONF" -N localhost || skip "slurmd did not start: $(tail -n 3 "$dir/slurmd.log" 2>/dev/null)"

for _ in $(seq 1 60); do
  state=$(sinfo -h -o %T 2>/dev/null | head -n 1)
  case "$state" in
    idle*) echo "slurm up: $SLURM_CONF ($cpus CPUs, $mem MB)"; exit 0 ;;
  esac
  sleep 1
done
skip "the node did not come up idle within 60 s (state '${state:-none}'): $(tail -n 3 "$dir/slurmd.log" 2>/dev/null)"
