# shellcheck shell=bash
# A one-node Slurm cluster on 127.0.0.1 inside a private directory, for the farm test and the
# farm benchmark. Source this file, then:
#   slurm_cluster_up DIR     start munged, slurmctld and slurmd with everything under DIR,
#                            export SLURM_CONF and wait until the node is idle
#   slurm_cluster_down DIR   stop them all (safe to call twice, and when the start failed)
# Needs root (slurmd runs jobs as their submitter), slurm-wlm and munge. No systemd, no
# cgroups, no accounting database: finished jobs are recorded in DIR/jobcomp.txt.

_slurm_free_port() { # prints PORT if nothing listens on it, else a free port the kernel picks
  python3 - "$1" <<'PY'
import socket, sys
want = int(sys.argv[1])
def free(port):
    s = socket.socket()
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        return s.getsockname()[1]
    except OSError:
        return None
    finally:
        s.close()
print(free(want) or free(0))
PY
}

slurm_cluster_up() {
  local dir=$1 host ncpu ctld_port slurmd_port key
  host=$(hostname -s)
  ncpu=$(nproc)
  mkdir -p "$dir"/munge "$dir"/state "$dir"/spool
  chmod 755 "$dir"
  # munged refuses a socket directory or key that another user could write or read.
  chown munge:munge "$dir"/munge
  chmod 755 "$dir"/munge
  key=/etc/munge/munge.key
  if [ ! -r "$key" ]; then
    key=$dir/munge/munge.key
    if command -v mungekey >/dev/null; then
      mungekey --create --keyfile="$key"
    else
      dd if=/dev/urandom of="$key" bs=1 count=1024 status=none
    fi
    chown munge:munge "$key"
    chmod 600 "$key"
  fi
  runuser -u munge -- /usr/sbin/munged --socket="$dir/munge/munge.socket" --key-file="$key" \
    --pid-file="$dir/munge/munged.pid" --log-file="$dir/munge/munged.log" \
    --seed-file="$dir/munge/munged.seed" || {
    echo "cluster: munged did not start:" >&2
    cat "$dir/munge/munged.log" >&2 2>/dev/null
    return 1
  }

  ctld_port=$(_slurm_free_port 6817)
  slurmd_port=$(_slurm_free_port 6818)
  [ "$slurmd_port" != "$ctld_port" ] || slurmd_port=$(_slurm_free_port 0)
  cat >"$dir/slurm.conf" <<CONF
ClusterName=volfxtest
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$dir/munge/munge.socket,cred_expire=5
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$dir/jobcomp.txt
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
SchedulerParameters=sched_interval=1,bf_interval=1
SlurmdParameters=config_overrides
ReturnToService=2
MpiDefault=none
MinJobAge=600
KillWait=5
NodeName=$host NodeAddr=127.0.0.1 CPUs=$ncpu State=UNKNOWN
PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
  export SLURM_CONF=$dir/slurm.conf
  /usr/sbin/slurmctld -f "$SLURM_CONF" -i || { echo "cluster: slurmctld did not start" >&2; return 1; }
  /usr/sbin/slurmd -f "$SLURM_CONF" || { echo "cluster: slurmd did not start" >&2; return 1; }
  local state
  for _ in $(seq 1 300); do
    state=$(sinfo -h -n "$host" -o %t 2>/dev/null || true)
    case "$state" in idle | mix | alloc) return 0 ;; esac
    sleep 0.2
  done
  echo "cluster: the node did not come up (state '$state'); logs:" >&2
  tail -n 20 "$dir/slurmctld.log" "$dir/slurmd.log" >&2 2>/dev/null
  return 1
}

_slurm_stop_pids() { # _slurm_stop_pids PIDFILE...: TERM them all, wait up to 10 s, then KILL
  local f pid pids=() alive
  for f in "$@"; do
    [ -s "$f" ] || continue
    pid=$(cat "$f" 2>/dev/null) || continue
    [ -n "$pid" ] && kill -TERM "$pid" 2>/dev/null && pids+=("$pid")
  done
  for _ in $(seq 1 100); do
    alive=0
    for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && alive=1; done
    [ $alive -eq 1 ] || return 0
    sleep 0.1
  done
  for pid in "${pids[@]}"; do kill -KILL "$pid" 2>/dev/null; done
  return 0
}

slurm_cluster_down() {
  local dir=$1
  [ -d "$dir" ] || return 0
  if [ -s "$dir/slurm.conf" ] && [ -s "$dir/slurmctld.pid" ]; then
    SLURM_CONF=$dir/slurm.conf scancel --quiet --full -u root 2>/dev/null || true
  fi
  _slurm_stop_pids "$dir/slurmd.pid" "$dir/slurmctld.pid"
  _slurm_stop_pids "$dir/munge/munged.pid"
  # Job steps left behind by a killed slurmd: any slurmstepd whose spool lies under DIR.
  local p
  for p in $(pgrep -x slurmstepd 2>/dev/null); do
    grep -qs "$dir" "/proc/$p/cmdline" && kill -KILL "$p" 2>/dev/null
  done
  return 0
}
