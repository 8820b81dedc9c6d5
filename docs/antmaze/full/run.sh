#!/usr/bin/env bash
# Issue 68: antmaze-sac and antmaze-sacmc seed 0 to 400,000 steps (sweep.yaml) from a clone of COMMIT, in
# the background (WORKERS=2 runs both at once, one core each; default one at a time; THREADS=2 gives a run two
# cores, for the one left once the other has finished); then the report (MC reward and KL curves) and one
# rendered episode of each final policy with its timeline.
#
#   bash docs/antmaze/full/run.sh start    # clone + install (once), then start or resume the sweep
#   bash docs/antmaze/full/run.sh sync     # finished runs' small files into runs/ here
#   bash docs/antmaze/full/run.sh status
#   bash docs/antmaze/full/run.sh report   # report/ (curves, MC reward and raw KL) from what is committed here
#   bash docs/antmaze/full/run.sh render   # episode-sac.mp4, episode-sacmc.mp4: one episode of each final policy
#   bash docs/antmaze/full/run.sh stop     # SIGTERM: the run in progress saves at its episode's end
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../../.." && pwd)"
COMMIT="$(cat "$HERE/COMMIT")"
WORK="${WORK:-/work/repro/antmaze-full}"
CODE="/work/repro/mcrl-$COMMIT"
. "$REPO/docs/background-runs.sh"
SWEEP="sweep .*--exp $WORK( |\$)"
WORKERS="${WORKERS:-1}"
THREADS="${THREADS:-1}"

case "${1:-status}" in
  sync)
    sync_runs "$CODE/.venv/bin/python" "$REPO" "$WORK" "$HERE"
    check_not_ignored "$REPO" "$HERE"/runs/*/config.json ;;
  status)
    arm_status antmaze "$WORK" "$HERE" ;;
  report)
    cd "$REPO" && .venv/bin/mcrl report docs/antmaze/full --out docs/antmaze/full/report ;;
  stop)
    pkill -TERM -f "$SWEEP" || { echo "not running"; exit 0; }
    while pgrep -f "$SWEEP" > /dev/null; do sleep 2; done; echo "stopped" ;;
  render)
    # the environment's default camera stays put while the ant walks out of view: render a copy of the run whose
    # config asks AntMaze (through env_kwargs, to gymnasium's AntEnv) for a top-down camera over the whole maze;
    # ARMS="sac:a0-s0" renders a finished arm while the other still runs
    for arm in ${ARMS:-sac:a0-s0 sacmc:a0.2-s0}; do
    TMP=$(mktemp -d)
    cp -r "$WORK/runs/${arm#*:}/config.json" "$WORK/runs/${arm#*:}/checkpoints" "$TMP/"
    "$CODE/.venv/bin/python" - "$TMP/config.json" <<'PY'
import json, sys
c = json.load(open(sys.argv[1]))
c["env_kwargs"] = {**c["env_kwargs"], "default_camera_config": {"distance": 20.0, "elevation": -90.0,
                                                                "azimuth": 90.0, "lookat": [0.0, 0.0, 0.0]}}
json.dump(c, open(sys.argv[1], "w"), indent=1)
PY
    MUJOCO_GL="${MUJOCO_GL:-egl}" "$CODE/.venv/bin/mcrl" render "$TMP" --episodes 1 --format mp4 \
      --out "$HERE/episode-${arm%%:*}.mp4" --no-progress
    rm -rf "$TMP"
    done ;;
  start)
    install_code "$REPO" "$CODE" "$COMMIT"
    restore_runs "$HERE" "$WORK"
    if pgrep -f "$SWEEP" > /dev/null; then echo "sweep already running (log $WORK.log)"; exit 0; fi
    (trap '' HUP; exec $(on_free_cores $((WORKERS * THREADS))) nice -n 10 "$CODE/.venv/bin/mcrl" sweep --file "$HERE/sweep.yaml" \
       --workers "$WORKERS" --threads-per-run "$THREADS" --exp "$WORK" \
       --no-progress) >> "$WORK.log" 2>&1 &
    echo "started the sweep (log $WORK.log)"
    [ -f "$WORK/provenance.json" ] || write_provenance "$WORK" "$COMMIT" \
      "mcrl sweep --file docs/antmaze/full/sweep.yaml --workers $WORKERS --threads-per-run $THREADS --exp EXP" \
      "git checkout $COMMIT && mcrl train --preset antmaze-sac --seed 0  (or --preset antmaze-sacmc)" ;;
  *) echo "usage: $0 start|sync|status|stop|report|render" >&2; exit 2 ;;
esac
