#!/usr/bin/env bash
# Start or resume issue 29's FetchPush arms (RND and Disagreement seeds 0-5, then ICM seeds 0-5, then RND and
# Disagreement seeds 6-11; fetchpush-sacmc-0.2's settings)
# from a clone of one fixed commit, in the background; compared with the reproduction's SAC and SAC-MC arms.
#
#   bash docs/intrinsic/fetchpush/run.sh start    # clone + install (once), then start or resume the sweep
#     WORKERS=N runs at once (default 1; `--threads-per-run 1` does not keep a run to one thread on jax 0.10.2, so
#     one run uses both cores: on the 2-core Zen 4 machine two runs went at about half speed each, so one at a time
#     finishes each run in half the time for about 8% fewer steps in all, and a run fits in one session, where a
#     machine that changes between sessions loses the run in progress; docs/studies/intrinsic-runs.md has the numbers)
#   bash docs/intrinsic/fetchpush/run.sh sync     # copy finished runs' small files here (then git commit them)
#   bash docs/intrinsic/fetchpush/run.sh status
#   bash docs/intrinsic/fetchpush/run.sh stop     # SIGTERM the sweep: the run in progress saves a checkpoint at its
#     episode's end and stops (a session's end may kill it without one, losing up to 10,000 steps); `start` resumes
#   bash docs/intrinsic/fetchpush/run.sh report   # docs/intrinsic/fetchpush/report, with SAC and SAC-MC
#   bash docs/intrinsic/fetchpush/run.sh solo icm 0   # one planned run (start or resume) outside the sweep, e.g.
#     one of a later phase; the sweep skips or resumes it later. Beside a running sweep both go at about half speed
#
# COMMIT is 39e2344: SAC-MC seed 7 re-run with it for 10,000 steps gave rows identical to the reproduction's
# (83e6d8d), so these arms and the reproduction's share one code path (docs/reproduction/fetchpush/rerun/).
# The runs live in $WORK (default /work/repro/intrinsic); checkpoints and buffers never enter git. Finished runs
# committed here are copied back into $WORK before starting, so a new machine resumes where git left off.
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../../.." && pwd)"
COMMIT="$(cat "$HERE/COMMIT")"
WORK="${WORK:-/work/repro/intrinsic}"
CODE="$WORK/mcrl-$COMMIT"
EXP=arms
WORKERS="${WORKERS:-1}"
SWEEP="sweep .*--exp $WORK/$EXP( |\$)"  # this experiment's `mcrl sweep` driver, for pgrep/pkill -f
. "$REPO/docs/background-runs.sh"
py() { if [ -x "$CODE/.venv/bin/python" ]; then "$CODE/.venv/bin/python" "$@"; else python3 "$@"; fi; }

case "${1:-status}" in
  sync)
    sync_runs py "$REPO" "$WORK/$EXP" "$HERE/$EXP"
    check_not_ignored "$REPO" "$HERE/$EXP"/runs/*/config.json ;;
  status)
    arm_status "$EXP" "$WORK/$EXP" "$HERE/$EXP" ;;
  stop)
    # times and the last logged step, so a slow stop can be told apart from a slow step
    arm_status "$EXP" "$WORK/$EXP" "$HERE/$EXP" | grep "in progress" || true
    t0=$(date +%s)
    pkill -TERM -f "$SWEEP" || { echo "no sweep running"; exit 0; }
    echo "SIGTERM sent to the sweep at $(date +%T)"
    while pgrep -f "$SWEEP" > /dev/null; do sleep 2; done
    echo "the sweep ended at $(date +%T), $(( $(date +%s) - t0 )) s after the signal"
    tail -n 3 "$WORK/$EXP.log" ;;
  report)
    # paths relative to the repository, so that the committed report names no machine's directories
    cd "$REPO" && .venv/bin/mcrl report "docs/intrinsic/fetchpush/$EXP" --with docs/reproduction/fetchpush/main \
      --out docs/intrinsic/fetchpush/report ;;
  start)
    install_code "$REPO" "$CODE" "$COMMIT"
    restore_runs "$HERE/$EXP" "$WORK/$EXP"
    if pgrep -f "$SWEEP" > /dev/null; then echo "sweep already running (log $WORK/$EXP.log)"; exit 0; fi
    # RND and Disagreement (the issue's two arms) first, then ICM, then their seeds 6-11, all into the same directory;
    # each skips finished runs
    (trap '' HUP; for f in sweep.yaml sweep-icm.yaml sweep-seeds-6-11.yaml; do
       "$CODE/.venv/bin/mcrl" sweep --file "$HERE/$f" --workers "$WORKERS" --threads-per-run 1 \
         --exp "$WORK/$EXP" --no-progress || exit
     done) >> "$WORK/$EXP.log" 2>&1 &
    echo "started the sweep: RND and Disagreement, then ICM, then seeds 6-11 (log $WORK/$EXP.log)"
    [ -f "$WORK/$EXP/provenance.json" ] || write_provenance "$WORK/$EXP" "$COMMIT" \
      "mcrl sweep --file docs/intrinsic/fetchpush/sweep.yaml --workers $WORKERS --threads-per-run 1 --exp EXP; the same with sweep-icm.yaml, then sweep-seeds-6-11.yaml" \
      "git checkout $COMMIT && XLA_FLAGS='--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1' mcrl train --preset fetchpush-sacmc-0.2 --set intrinsic=rnd --seed N  (or icm, disagreement)" ;;
  solo)
    # the run the sweep would make (same config, directory, and one-thread flags from the sweep's own thread_env),
    # trained by `mcrl train` beside the sweep; it locks only its run directory, not the experiment (a sweep worker
    # that reaches the run while this trains it is refused by that lock: the sweep goes on with its other runs)
    case "${2:-}" in rnd|icm|disagreement) ;; *) echo "usage: $0 solo rnd|icm|disagreement SEED" >&2; exit 2 ;; esac
    [[ "${3:-}" =~ ^[0-9]+$ ]] || { echo "usage: $0 solo $2 SEED (a seed such as 0)" >&2; exit 2; }
    dir="$WORK/$EXP/runs/intrinsic=$2-s$3"
    [ -f "$dir/done" ] && { echo "intrinsic=$2-s$3 already finished"; exit 0; }
    if ls -d "$dir"/checkpoints/step_* > /dev/null 2>&1; then how=(--resume "$dir")
    elif [ -e "$dir" ]; then echo "error: $dir has no checkpoint to resume: remove it to start the run over" >&2; exit 1
    else mkdir -p "$WORK/$EXP/runs"; how=(--preset fetchpush-sacmc-0.2 --set "intrinsic=$2" --seed "$3" --run-dir "$dir"); fi
    install_code "$REPO" "$CODE" "$COMMIT"
    mapfile -d '' one_thread < <("$CODE/.venv/bin/python" -c \
      'from mcrl.sweep.worker import thread_env; print("\0".join(f"{k}={v}" for k, v in thread_env(1).items()), end="")')
    (trap '' HUP; env "${one_thread[@]}" "$CODE/.venv/bin/mcrl" train "${how[@]}" --no-progress) \
      >> "$WORK/$EXP-solo.log" 2>&1 &
    echo "training intrinsic=$2-s$3 alone (log $WORK/$EXP-solo.log)" ;;
  *) echo "usage: $0 start|stop|sync|status|report|solo" >&2; exit 2 ;;
esac
