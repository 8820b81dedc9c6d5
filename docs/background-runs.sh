# Shared by the run.sh scripts of long experiments (docs/*/*/run.sh: reproduction, intrinsic, confirmatory,
# schedule, AntMaze): install one fixed commit, bring committed runs back, sync finished runs into git, report
# progress.
# Sourced, not run; every function takes its directories as arguments.

# this machine, as recorded in provenance.json and in each newly finished run's machine.json
machine_name() {
  echo "$(lscpu | sed -n 's/^Model name: *//p'), family $(grep -m1 'cpu family' /proc/cpuinfo | cut -d: -f2 | tr -d ' ') model $(grep -m1 '^model\s' /proc/cpuinfo | cut -d: -f2 | tr -d ' '), $(nproc) cores"
}

# install_code REPO CODE COMMIT [EXTRAS]: a clone of REPO at COMMIT in CODE with its .venv (once). Done means
# make install's .venv/.installed and, with EXTRAS, a .venv/.EXTRAS marker written after they installed, so an
# install cut short is finished by the next start
install_code() {
  local extra="${4:-}"
  [ -f "$2/.venv/.installed" ] && { [ -z "$extra" ] || [ -f "$2/.venv/.$extra" ]; } && return 0
  mkdir -p "$(dirname "$2")"
  [ -d "$2" ] || { git clone -q "$1" "$2" && git -C "$2" checkout -q "$3"; }
  (cd "$2" && make install && if [ -n "$extra" ]; then
     # the pins where the commit has them (older commits pin in pyproject.toml only)
     .venv/bin/pip install -q $([ -f constraints.txt ] && echo -c constraints.txt) -e ".[$extra]" && touch ".venv/.$extra"; fi)
}

# restore_runs COMMITTED WORK: finished runs from git back into the work directory (the sweep skips them), and
# the committed sweep.json and provenance.json where the work directory has none, so a new machine resumes where
# git left off (without provenance.json, `start` would write a fresh one and the next sync would drop the
# committed command and the machines of earlier runs)
restore_runs() {
  if [ -d "$1/runs" ]; then mkdir -p "$2/runs"; cp -rn "$1/runs/." "$2/runs/"; fi
  local f
  for f in sweep.json provenance.json; do
    if [ -f "$1/$f" ] && [ ! -f "$2/$f" ]; then mkdir -p "$2" && cp "$1/$f" "$2/"; fi
  done
}

# sync_runs PYTHON REPO WORK COMMITTED: finished runs' small files into git's tree (scripts/sync_runs.py, stdlib
# only, records the machine of each newly finished run)
sync_runs() {
  [ -d "$3" ] || return 0
  "$1" "$2/scripts/sync_runs.py" "$3" "$4" --machine "$(machine_name)"
}

# check_not_ignored REPO FILE...: a synced file git ignores would be lost with the machine: say so now
check_not_ignored() {
  local repo="$1"; shift
  if git -C "$repo" check-ignore -q "$@" 2>/dev/null; then
    echo "error: git ignores synced run files ($1 ...): fix .gitignore before committing" >&2; return 1
  fi
}

# arm_status NAME WORK COMMITTED: finished and committed runs, then each run in progress at its last logged step,
# with its speed over its last ten logged rows and the time left at that speed (the final evaluation not counted)
arm_status() {
  echo "$1: $(ls -d "$2"/runs/*/done 2>/dev/null | wc -l) finished;" \
       "$(ls -d "$3"/runs/*/done 2>/dev/null | wc -l) committed"
  local d total
  for d in "$2"/runs/*/; do
    if [ ! -f "$d/done" ] && [ -f "$d/metrics.csv" ]; then
      total="$(sed -n 's/.*"total_steps": *\([0-9]*\).*/\1/p' "$d/config.json" 2>/dev/null | head -1)"
      # columns 1 and 2 are step and time_s; a resume restarts time_s, so only rows after the last drop count
      tail -n 11 "$d/metrics.csv" | awk -F, -v name="$1/$(basename "$d")" -v t="${total:-0}" '
        $1 == "step" { next }
        { if (n && $2 < t1) n = 0; if (!n) { s0 = $1; t0 = $2 } s1 = $1; t1 = $2; n++ }
        END {
          if (!n) { printf "  in progress: %s at step 0 (no row logged yet)\n", name; exit }
          printf "  in progress: %s at step %d of %s", name, s1, (t ? t : "?")
          if (n > 1 && t1 > t0 && t > s1) { r = (s1 - s0) / (t1 - t0); printf ", %.0f steps/s: %.0f min left", r, (t - s1) / r / 60 }
          printf "\n" }'
      run_footprint "$d"
    fi
  done
}

# run_footprint RUNDIR: the memory of the process that holds the run's lock (resident now and at its peak: the
# replay buffer, the networks and the JAX runtime together) and the size of its checkpoints, as issue 68 asks of
# the AntMaze runs
run_footprint() {
  local lock pid ckpt
  lock="$(cd "$1" && pwd)/.lock"
  pid="$(find /proc/[0-9]*/fd -maxdepth 1 -lname "$lock" 2>/dev/null | head -1 | cut -d/ -f3 || true)"
  ckpt="$(du -sm "$1/checkpoints" 2>/dev/null | cut -f1 || true)"
  [ -n "$pid" ] || [ -n "$ckpt" ] || return 0
  printf "    "
  [ -z "$pid" ] || awk '/^VmRSS/ { r = $2 } /^VmHWM/ { h = $2 }
    END { printf "process %d MiB resident (peak %d MiB), ", r / 1024, h / 1024 }' "/proc/$pid/status"
  echo "checkpoints ${ckpt:-0} MiB"
}

# write_provenance WORK COMMIT COMMAND RERUN_ONE_SEED: provenance.json of a sweep's directory, once the sweep
# has made the directory (it wants to create it itself)
write_provenance() {
  for _ in $(seq 120); do [ -f "$1/sweep.json" ] && break; sleep 1; done
  printf '{"commit": "%s", "machine": "%s", "command": "%s", "rerun_one_seed": "%s"}\n' \
    "$2" "$(machine_name)" "$3" "$4" > "$1/provenance.json"
}

# on_free_cores N: "taskset -c LIST" naming N cores that no pinned mcrl process (one allowed fewer cores than this
# shell) holds now, or nothing when fewer are free. The pinned commits these runs use (b5e5eda, 245cd0e) start
# every sweep's first worker on the first core of its mask, so two sweeps side by side shared core 0 while core 1
# idled (docs/performance.md#a-sweeps-workers-and-their-cores); given a mask of free cores, a sweep keeps to them.
on_free_cores() {
  local cores
  cores="$(python3 - "$1" <<'PY'
import os, sys
mine, used = os.sched_getaffinity(0), set()
for p in filter(str.isdigit, os.listdir("/proc")):
    try:
        if b"mcrl" in open(f"/proc/{p}/cmdline", "rb").read() and os.sched_getaffinity(int(p)) < mine:
            used |= os.sched_getaffinity(int(p))
    except OSError:  # gone, or not ours to read
        pass
free = sorted(mine - used)[: int(sys.argv[1])]
print(",".join(map(str, free)) if len(free) == int(sys.argv[1]) else "")
PY
)"
  [ -z "$cores" ] || echo "taskset -c $cores"
}
