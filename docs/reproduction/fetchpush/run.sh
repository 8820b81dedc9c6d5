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
. "$REPO/docs/background-runs.sh"
case "$cmd" in
  sync)
    for arm in $ARMS; do sync_runs "$CODE/.venv/bin/python" "$REPO" "$WORK/$arm" "$HERE/$arm"; done
    check_not_ignored "$REPO" "$HERE"/*/runs/*/config.json ;;
  status)
    for arm in $ARMS; do arm_status "$arm" "$WORK/$arm" "$HERE/$arm"; done ;;
  start)
    install_code "$REPO" "$CODE" "$COMMIT" bench
    for arm in $ARMS; do restore_runs "$HERE/$arm" "$WORK/$arm"; done
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
      write_provenance "$WORK/main" "$COMMIT" "mcrl sweep --preset fetchpush-sac --alphas 0,0.2 --seeds ${SEEDS:-12} --workers ${WORKERS:-2} --threads-per-run 1 --exp EXP" \
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
      install_code "$REPO" "$SB3_CODE" "$SB3_COMMIT" bench
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
      write_provenance "$WORK/code-variant" "$COMMIT" "mcrl sweep --preset fetchpush-sacmc-0.2 --set mc_reduction=batch --set mc_state=full --seeds 6 --workers ${VARIANT_WORKERS:-2} --threads-per-run 1 --exp EXP" \
        "git checkout $COMMIT && XLA_FLAGS='--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1' mcrl train --preset fetchpush-sacmc-0.2 --set mc_reduction=batch --set mc_state=full --seed N"
    fi ;;
  *) echo "usage: $0 start|sync|status" >&2; exit 2 ;;
esac
