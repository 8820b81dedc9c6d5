#!/usr/bin/env bash
# Issue 67 item 5: the pilot, then the exploratory FetchPush arm of a `success` schedule, from a clone of one fixed
# commit (COMMIT), in the background at nice 10, after the confirmatory experiment's batches (docs/confirmatory).
#
#   bash docs/intrinsic/schedule/run.sh pilot     # clone + install (once), start or resume the pilot (pilot.yaml)
#   bash docs/intrinsic/schedule/run.sh start     # the same for the arm (sweep.yaml), once the pilot is read
#   bash docs/intrinsic/schedule/run.sh sync      # finished runs' small files here (then git commit them)
#   bash docs/intrinsic/schedule/run.sh status
#   bash docs/intrinsic/schedule/run.sh stop      # SIGTERM: each run in progress saves at its episode's end
#   bash docs/intrinsic/schedule/run.sh report    # report/: the arm beside the reproduction's SAC and SAC-MC 0.2
#
# The runs live in $WORK (default /work/repro/schedule); checkpoints and buffers never enter git. WORKERS runs at
# once (default 1: the confirmatory experiment has the other core).
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../../.." && pwd)"
COMMIT="$(cat "$HERE/COMMIT")"
WORK="${WORK:-/work/repro/schedule}"
CODE="/work/repro/mcrl-$COMMIT"
WORKERS="${WORKERS:-1}"
. "$REPO/docs/background-runs.sh"
sweep_of() { echo "sweep .*--exp $WORK/$1( |\$)"; }

launch() {  # launch EXP FILE: start or resume the sweep of FILE into WORK/EXP
  install_code "$REPO" "$CODE" "$COMMIT"
  restore_runs "$HERE/$1" "$WORK/$1"
  if pgrep -f "$(sweep_of "$1")" > /dev/null; then echo "$1 already running (log $WORK/$1.log)"; return 0; fi
  (trap '' HUP; exec $(on_free_cores "$WORKERS") nice -n 10 "$CODE/.venv/bin/mcrl" sweep --file "$HERE/$2" \
     --workers "$WORKERS" --threads-per-run 1 --exp "$WORK/$1" --no-progress) >> "$WORK/$1.log" 2>&1 &
  echo "started $1 (log $WORK/$1.log)"
  [ -f "$WORK/$1/provenance.json" ] || write_provenance "$WORK/$1" "$COMMIT" \
    "mcrl sweep --file docs/intrinsic/schedule/$2 --workers $WORKERS --threads-per-run 1 --exp EXP" \
    "git checkout $COMMIT && mcrl train --preset fetchpush-sacmc-0.4 --set intrinsic_schedule=success --seed N"
}

case "${1:-status}" in
  pilot) mkdir -p "$WORK"; launch pilot pilot.yaml ;;
  start) mkdir -p "$WORK"; launch arm sweep.yaml ;;
  sync)
    for e in pilot arm; do
      sync_runs "$CODE/.venv/bin/python" "$REPO" "$WORK/$e" "$HERE/$e"
      [ ! -d "$HERE/$e/runs" ] || check_not_ignored "$REPO" "$HERE/$e"/runs/*/config.json
    done ;;
  status) for e in pilot arm; do arm_status "$e" "$WORK/$e" "$HERE/$e"; done ;;
  stop)
    for e in pilot arm; do pkill -TERM -f "$(sweep_of "$e")" && echo "SIGTERM sent to $e" || true; done
    while pgrep -f "$(sweep_of pilot)|$(sweep_of arm)" > /dev/null; do sleep 2; done; echo "stopped" ;;
  report)
    cd "$REPO" && .venv/bin/mcrl report docs/intrinsic/schedule/arm --with docs/reproduction/fetchpush/main \
      --out docs/intrinsic/schedule/report ;;
  *) echo "usage: $0 pilot|start|sync|status|stop|report" >&2; exit 2 ;;
esac
