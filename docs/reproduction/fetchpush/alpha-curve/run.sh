#!/usr/bin/env bash
# Issue 50: the rest of the thesis' FetchPush alpha curve, fetchpush-sacmc-{0.4,0.6,0.8,1.0} seeds 0-5 (150,000
# steps, 100-episode final evaluations), from a clone of COMMIT: the commit of the reproduction's SAC and SAC-MC 0.2
# arms (../main) they are compared with, so every arm of the curve comes from one code version (issue 49 kept those
# arms: docs/studies/sac-baseline/README.md). Seed-major order, so a partial curve has the same seeds at every alpha.
#
#   bash docs/reproduction/fetchpush/alpha-curve/run.sh start   # clone + install (once), then start or resume
#     WORKERS=N runs at once (default 1, one thread each); SEEDS=N seeds 0..N-1 of each alpha (default 6);
#     ALPHAS=a,b only these alphas (default all four): the extension is ALPHAS=X,Y SEEDS=12, which adds seeds 6-11
#     of two arms to the same sweep (finished seeds are skipped) and records its command in provenance.json
#   bash docs/reproduction/fetchpush/alpha-curve/run.sh sync    # finished runs' small files here (then commit)
#   bash docs/reproduction/fetchpush/alpha-curve/run.sh status
#   bash docs/reproduction/fetchpush/alpha-curve/run.sh stop    # SIGTERM to the sweep: it stops. At COMMIT the sweep
#     ends without its run saving (today's mcrl saves at the episode's end; checked 2026-11-28 with a FetchReach sweep
#     started as `start` starts it), so a stop loses the run's work since its last checkpoint (every 10,000 steps)
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../../../.." && pwd)"
COMMIT="$(cat "$HERE/COMMIT")"
WORK="${WORK:-/work/repro/alpha-curve}"
CODE="/work/repro/mcrl-$COMMIT"
. "$REPO/docs/background-runs.sh"
SWEEP="sweep .*--exp $WORK( |\$)"
ALL=0.4,0.6,0.8,1.0
ALPHAS="${ALPHAS:-$ALL}"

# record_extension PROVENANCE COMMAND: a later sweep into the same directory (more seeds of some arms) joins the
# provenance's list of extensions once, so the committed record names every command that made its runs
record_extension() {
  "$CODE/.venv/bin/python" - "$1" "$2" <<'PY'
import json, sys
path, command = sys.argv[1], sys.argv[2]
doc = json.load(open(path))
if command not in doc.setdefault("extensions", []):
    doc["extensions"].append(command)
    json.dump(doc, open(path, "w"))
PY
}

case "${1:-status}" in
  sync)
    sync_runs "$CODE/.venv/bin/python" "$REPO" "$WORK" "$HERE"
    check_not_ignored "$REPO" "$HERE"/runs/*/config.json ;;
  status)
    arm_status alpha-curve "$WORK" "$HERE" ;;
  stop)
    pkill -TERM -f "$SWEEP" || { echo "no sweep running"; exit 0; }
    while pgrep -f "$SWEEP" > /dev/null; do sleep 2; done; echo "stopped" ;;
  start)
    install_code "$REPO" "$CODE" "$COMMIT" bench
    restore_runs "$HERE" "$WORK"
    if pgrep -f "$SWEEP" > /dev/null; then echo "sweep already running (log $WORK.log)"; exit 0; fi
    (trap '' HUP; "$CODE/.venv/bin/mcrl" sweep --preset fetchpush-sac --alphas "$ALPHAS" --seeds "${SEEDS:-6}" \
       --workers "${WORKERS:-1}" --threads-per-run 1 --exp "$WORK" --no-progress) >> "$WORK.log" 2>&1 &
    echo "started the alpha-curve sweep (log $WORK.log)"
    recorded="mcrl sweep --preset fetchpush-sac --alphas $ALPHAS --seeds ${SEEDS:-6} --workers ${WORKERS:-1} \
--threads-per-run 1 --exp EXP"
    if [ "$ALPHAS" != "$ALL" ] && [ -f "$WORK/provenance.json" ]; then
      record_extension "$WORK/provenance.json" "$recorded"
    fi
    [ -f "$WORK/provenance.json" ] || write_provenance "$WORK" "$COMMIT" "$recorded" \
      "git checkout $COMMIT && XLA_FLAGS='--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1' mcrl train --preset fetchpush-sacmc-0.4 --seed N  (or 0.6, 0.8, 1.0)" ;;
  *) echo "usage: $0 start|stop|sync|status" >&2; exit 2 ;;
esac
