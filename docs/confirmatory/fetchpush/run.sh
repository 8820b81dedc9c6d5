#!/usr/bin/env bash
# The confirmatory FetchPush experiment (issue 65): `mcrl decide plan.yaml` from a clone of the plan's pinned commit,
# in the background, batch by batch until its claims are decided.
#
#   bash docs/confirmatory/fetchpush/run.sh start    # clone + install the commit (once), bring committed runs and
#                                                    # looks back, then start or resume `mcrl decide` (nice 10)
#   bash docs/confirmatory/fetchpush/run.sh sync     # finished runs' small files and new looks here (then commit)
#   bash docs/confirmatory/fetchpush/run.sh status   # looks taken, runs finished, runs in progress
#   bash docs/confirmatory/fetchpush/run.sh stop     # SIGTERM: each running run saves at its episode's end
#   bash docs/confirmatory/fetchpush/run.sh report   # the report (with stable-baselines3's 12 seeds beside, as
#                                                    # exploratory) and the README's verdict, by main's mcrl
#
# The runs live in $WORK (default /work/repro/confirmatory): checkpoints and buffers never enter git. WORKERS runs at
# once (default 2, one core each). A batch's look is taken by `mcrl decide` once all its runs have finished; sync
# copies looks.jsonl here only by appending (a committed look is never rewritten).
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../../.." && pwd)"
COMMIT="$(sed -n 's/^commit: *\([0-9a-f]*\).*/\1/p' "$HERE/plan.yaml")"
WORK="${WORK:-/work/repro/confirmatory}"
CODE="/work/repro/mcrl-$COMMIT"
. "$REPO/docs/background-runs.sh"
DECIDE="decide $WORK/plan.yaml"

# append_looks FROM TO: TO's records must be FROM's first ones; copy FROM's further records onto TO
append_looks() {
  [ -f "$1" ] || return 0
  local have=0
  [ -f "$2" ] && have="$(wc -l < "$2")"
  if [ "$have" -gt 0 ] && ! cmp -s "$2" <(head -n "$have" "$1"); then
    echo "error: $2 is not a prefix of $1: looks are never rewritten; find out why before syncing" >&2; return 1
  fi
  tail -n +"$((have + 1))" "$1" >> "$2"
}

case "${1:-status}" in
  sync)
    sync_runs "$CODE/.venv/bin/python" "$REPO" "$WORK" "$HERE"
    append_looks "$WORK/looks.jsonl" "$HERE/looks.jsonl"
    [ ! -d "$HERE/runs" ] || check_not_ignored "$REPO" "$HERE"/runs/*/config.json ;;
  status)
    echo "looks: $( [ -f "$WORK/looks.jsonl" ] && wc -l < "$WORK/looks.jsonl" || echo 0) taken;" \
         "$( [ -f "$HERE/looks.jsonl" ] && wc -l < "$HERE/looks.jsonl" || echo 0) committed"
    arm_status confirmatory "$WORK" "$HERE"
    pgrep -f "$DECIDE" > /dev/null && echo "mcrl decide is running (log $WORK.log)" || echo "mcrl decide is not running" ;;
  report)
    "$REPO/.venv/bin/mcrl" report "$HERE" --with "$REPO/docs/reproduction/fetchpush/sb3-sac=sb3-sac" \
      --readme "$REPO/README.md" ;;
  stop)
    pkill -TERM -f "$DECIDE" || { echo "not running"; exit 0; }
    while pgrep -f "$DECIDE" > /dev/null; do sleep 2; done; echo "stopped" ;;
  start)
    install_code "$REPO" "$CODE" "$COMMIT"
    mkdir -p "$WORK"
    if [ -f "$WORK/plan.yaml" ] && ! cmp -s "$WORK/plan.yaml" "$HERE/plan.yaml"; then
      echo "error: $WORK/plan.yaml differs from the committed plan: a plan never changes" >&2; exit 1
    fi
    cp -n "$HERE/plan.yaml" "$WORK/plan.yaml"
    restore_runs "$HERE" "$WORK"
    append_looks "$HERE/looks.jsonl" "$WORK/looks.jsonl"  # a new machine: the committed looks come back
    if pgrep -f "$DECIDE" > /dev/null; then echo "already running (log $WORK.log)"; exit 0; fi
    (trap '' HUP; nice -n 10 "$CODE/.venv/bin/mcrl" $DECIDE --workers "${WORKERS:-2}" --threads-per-run 1 \
       --no-progress) >> "$WORK.log" 2>&1 &
    echo "started mcrl decide (log $WORK.log)"
    [ -f "$WORK/provenance.json" ] || write_provenance "$WORK" "$COMMIT" \
      "mcrl decide plan.yaml --workers ${WORKERS:-2} --threads-per-run 1 (nice -n 10)" \
      "git checkout $COMMIT && XLA_FLAGS='--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1' mcrl train --preset fetchpush-sac --set intrinsic_alpha=A --seed N" ;;
  *) echo "usage: $0 start|stop|sync|status|report" >&2; exit 2 ;;
esac
