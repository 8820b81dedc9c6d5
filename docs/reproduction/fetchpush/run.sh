#!/usr/bin/env bash
# Start or resume the FetchPush reproduction (issue 9) from a clone of one fixed commit, in the background.
#
#   bash docs/reproduction/fetchpush/run.sh start   # clone + install (once), then start what is unfinished
#     WORKERS=N  runs at once in the main sweep (2);  SEEDS=N  seeds 0..N-1 of each main arm (12: issue 26 added
#     seeds 6-11 to issue 9's 0-5);  MAIN=0  leave the main sweep alone
#     WITH_SB3=1 the stable-baselines3 reference too (SB3_SEEDS, default "0 1 2 3 4 5", one after another;
#     SB3_THREADS, default 1, as every committed run);  WITH_VARIANT=1 the third arm (VARIANT_WORKERS runs at once, 2)
#   bash docs/reproduction/fetchpush/run.sh sync    # copy finished runs' small files here (then git commit them)
#   bash docs/reproduction/fetchpush/run.sh status
#
# The runs live in $WORK (default /work/repro): checkpoints and buffers never enter git. Finished runs committed
# under this directory are copied back into $WORK before starting, so a new machine resumes where git left off
# (a run in progress restarts from its last checkpoint if $WORK survived, from scratch otherwise).
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../../.." && pwd)"
COMMIT="$(cat "$HERE/COMMIT")"          # the code version of every run
WORK="${WORK:-/work/repro}"
CODE="$WORK/mcrl-$COMMIT"
ARMS="main code-variant sb3-sac"        # experiment dirs: SAC + SAC-MC 0.2; the thesis code's variant; SB3

cmd="${1:-status}"
# this machine, as recorded in provenance.json for the runs it finishes
machine="$(lscpu | sed -n 's/^Model name: *//p'), family $(grep -m1 'cpu family' /proc/cpuinfo | cut -d: -f2 | tr -d ' ') model $(grep -m1 '^model\s' /proc/cpuinfo | cut -d: -f2 | tr -d ' '), $(nproc) cores"
sync() {  # the working tree's sync_runs.py (stdlib only), which records the machine of each newly finished run
  for arm in $ARMS; do
    [ -d "$WORK/$arm" ] && "$CODE/.venv/bin/python" "$REPO/benchmarks/sync_runs.py" "$WORK/$arm" "$HERE/$arm" --machine "$machine"
  done
  return 0
}
case "$cmd" in
  sync)
    sync
    # a file git ignores would be lost with the machine: say so now, not when it is gone
    if git -C "$REPO" check-ignore -q "$HERE"/*/runs/*/config.json 2>/dev/null; then
      echo "error: git ignores the synced run files under $HERE: fix .gitignore before committing" >&2; exit 1
    fi ;;
  status)
    for arm in $ARMS; do
      echo "$arm: $(ls -d "$WORK/$arm"/runs/*/done 2>/dev/null | wc -l) finished;" \
           "$(ls -d "$HERE/$arm"/runs/*/done 2>/dev/null | wc -l) committed"
    done
    for d in "$WORK"/*/runs/*/; do  # runs in progress: the last logged step
      if [ ! -f "$d/done" ] && [ -f "$d/metrics.csv" ]; then
        echo "  in progress: $(basename "$(dirname "$(dirname "$d")")")/$(basename "$d") at step $(tail -1 "$d/metrics.csv" | cut -d, -f1)"
      fi
    done ;;
  start)
    if [ ! -x "$CODE/.venv/bin/mcrl" ]; then
      git clone -q "$REPO" "$CODE" && git -C "$CODE" checkout -q "$COMMIT"
      (cd "$CODE" && make install && .venv/bin/pip install -q -e ".[bench]")
    fi
    for arm in $ARMS; do  # finished runs from git: the sweep skips them
      if [ -d "$HERE/$arm/runs" ]; then mkdir -p "$WORK/$arm/runs"; cp -rn "$HERE/$arm/runs/." "$WORK/$arm/runs/"; fi
      if [ -f "$HERE/$arm/sweep.json" ] && [ ! -f "$WORK/$arm/sweep.json" ]; then
        mkdir -p "$WORK/$arm" && cp "$HERE/$arm/sweep.json" "$WORK/$arm/"
      fi
    done
    mk_prov() {  # $1 arm, $2 command, $3 one-seed command; after the sweep made its directory (it wants it empty)
      for _ in $(seq 120); do [ -f "$WORK/$1/sweep.json" ] && break; sleep 1; done
      printf '{"commit": "%s", "machine": "%s", "command": "%s", "rerun_one_seed": "%s"}\n' \
        "$COMMIT" "$machine" "$2" "$3" > "$WORK/$1/provenance.json"
    }
    M="$CODE/.venv/bin/mcrl"
    mkdir -p "$WORK/sb3-sac/runs"
    # SAC and SAC-MC 0.2, seed-major order (s0 of both arms first), 2 runs at a time, 1 thread each; the sweep
    # merges the new seeds into the committed sweep.json and skips the runs that are done
    if [ "${MAIN:-1}" = 0 ]; then
      echo "main sweep not started (MAIN=0)"
    elif pgrep -f "sweep .*--exp $WORK/main( |$)" > /dev/null; then
      echo "main sweep already running (log $WORK/main.log)"
    else
      nohup "$M" sweep --preset fetchpush-sac --alphas 0,0.2 --seeds "${SEEDS:-12}" --workers "${WORKERS:-2}" --threads-per-run 1 \
        --exp "$WORK/main" --no-progress > "$WORK/main.log" 2>&1 &
      echo "started main sweep (log $WORK/main.log)"
      # the machine and commit of this sweep's runs (not written when another start only adds SB3 runs)
      mk_prov main "mcrl sweep --preset fetchpush-sac --alphas 0,0.2 --seeds ${SEEDS:-12} --workers ${WORKERS:-2} --threads-per-run 1 --exp EXP" \
        "git checkout $COMMIT && XLA_FLAGS='--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1' mcrl train --preset fetchpush-sac --seed N  (or --preset fetchpush-sacmc-0.2)"
    fi
    # The stable-baselines3 reference, SB3_SEEDS (default 0 1 2 3 4 5) one after another, from its own commit
    # (sb3-sac/COMMIT: the runner gained checkpoints after COMMIT). A seed already running is left alone, so a
    # second `start` with other SB3_SEEDS runs them beside the first, and a chain skips a seed begun or finished
    # since. Checkpoints (every 10,000 steps) live on this machine only: a run unfinished when the machine goes
    # restarts from scratch on the next one.
    if [ "${WITH_SB3:-0}" = 1 ]; then
      SB3_COMMIT="$(cat "$HERE/sb3-sac/COMMIT")"
      SB3_CODE="$WORK/mcrl-$SB3_COMMIT"
      if [ ! -x "$SB3_CODE/.venv/bin/python" ] || [ ! -f "$SB3_CODE/.venv/.bench" ]; then
        [ -d "$SB3_CODE" ] || { git clone -q "$REPO" "$SB3_CODE" && git -C "$SB3_CODE" checkout -q "$SB3_COMMIT"; }
        (cd "$SB3_CODE" && make install && .venv/bin/pip install -q -e ".[bench]" && touch .venv/.bench)
      fi
      sb3_running() { pgrep -f "parity_sb3.py sb3 .*--run-dir $1( |$)" > /dev/null; }
      seeds=()
      for s in ${SB3_SEEDS:-0 1 2 3 4 5}; do
        d="$WORK/sb3-sac/runs/sb3-sac-s$s"
        if [ -f "$d/done" ]; then continue; fi
        if sb3_running "$d"; then echo "stable-baselines3 seed $s already running"; continue; fi
        seeds+=("$s")
      done
      if [ "${#seeds[@]}" -gt 0 ]; then
        log="$WORK/sb3-s$(IFS=-; echo "${seeds[*]}").log"
        (trap '' HUP; for s in "${seeds[@]}"; do
           d="$WORK/sb3-sac/runs/sb3-sac-s$s"
           # checked again: another start may have run or begun this seed since (no second writer on one run)
           if [ -f "$d/done" ] || sb3_running "$d"; then continue; fi
           if ls "$d"/sb3_checkpoints/step_*/state.pkl > /dev/null 2>&1; then args=(--resume)
           else args=(--preset fetchpush-sac --seed "$s" --overwrite); fi
           "$SB3_CODE/.venv/bin/python" "$SB3_CODE/benchmarks/parity_sb3.py" sb3 "${args[@]}" \
             --threads "${SB3_THREADS:-1}" --run-dir "$d" --no-progress
         done) > "$log" 2>&1 &
        echo "started stable-baselines3 seed(s) ${seeds[*]} (log $log)"
      fi
    fi
    if [ "${WITH_VARIANT:-0}" = 1 ] && pgrep -f "sweep .*--exp $WORK/code-variant( |$)" > /dev/null; then
      echo "code-variant sweep already running"
    elif [ "${WITH_VARIANT:-0}" = 1 ]; then  # the thesis' code's MC reward: after the first two arms
      nohup "$M" sweep --preset fetchpush-sacmc-0.2 --set mc_reduction=batch --set mc_state=full --seeds 6 \
        --workers "${VARIANT_WORKERS:-2}" --threads-per-run 1 --exp "$WORK/code-variant" --no-progress > "$WORK/code-variant.log" 2>&1 &
      echo "started the code-variant sweep (log $WORK/code-variant.log)"
      mk_prov code-variant "mcrl sweep --preset fetchpush-sacmc-0.2 --set mc_reduction=batch --set mc_state=full --seeds 6 --workers ${VARIANT_WORKERS:-2} --threads-per-run 1 --exp EXP" \
        "git checkout $COMMIT && XLA_FLAGS='--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1' mcrl train --preset fetchpush-sacmc-0.2 --set mc_reduction=batch --set mc_state=full --seed N"
    fi ;;
  *) echo "usage: $0 start|sync|status" >&2; exit 2 ;;
esac
