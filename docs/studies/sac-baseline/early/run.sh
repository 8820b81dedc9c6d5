#!/usr/bin/env bash
# Issue 49 item 3: early courses (20,000 steps) of mcrl's SAC with squash_correction=exact and =epsilon, seeds 0-5
# (`mcrl sweep`, sweep.yaml), and of stable-baselines3's SAC at the same settings, seeds 0-5 (parity_sb3.py, which
# at COMMIT also records saturated_share, logp_gap and train_goal_moved), all from a clone of COMMIT, in the
# background, one run at a time per chain (WORKERS=N for the mcrl sweep).
#
#   bash docs/studies/sac-baseline/early/run.sh start   # clone + install (once), then start or resume both chains
#   bash docs/studies/sac-baseline/early/run.sh sync    # finished runs' small files into mcrl/ and sb3/ here
#   bash docs/studies/sac-baseline/early/run.sh status
#   bash docs/studies/sac-baseline/early/run.sh table   # the early-course table (docs/studies/sac-baseline/README.md), from what is here
set -euo pipefail
HERE="$(cd "$(dirname "$0")" && pwd)"
REPO="$(cd "$HERE/../../../.." && pwd)"
COMMIT="$(cat "$HERE/COMMIT")"
WORK="${WORK:-/work/repro/early}"
CODE="/work/repro/mcrl-$COMMIT"
. "$REPO/docs/background-runs.sh"
SWEEP="sweep .*--exp $WORK/mcrl( |\$)"

case "${1:-status}" in
  sync)
    for arm in mcrl sb3; do sync_runs "$CODE/.venv/bin/python" "$REPO" "$WORK/$arm" "$HERE/$arm"; done
    check_not_ignored "$REPO" "$HERE"/*/runs/*/config.json ;;
  status)
    for arm in mcrl sb3; do arm_status "$arm" "$WORK/$arm" "$HERE/$arm"; done ;;
  table)
    "$REPO/.venv/bin/python" "$HERE/table.py" "$HERE" ;;
  start)
    install_code "$REPO" "$CODE" "$COMMIT" bench
    for arm in mcrl sb3; do restore_runs "$HERE/$arm" "$WORK/$arm"; done
    mkdir -p "$WORK/sb3/runs"
    if pgrep -f "$SWEEP" > /dev/null; then echo "mcrl sweep already running"; else
      (trap '' HUP; "$CODE/.venv/bin/mcrl" sweep --file "$HERE/sweep.yaml" --workers "${WORKERS:-1}" --threads-per-run 1 \
         --exp "$WORK/mcrl" --no-progress) >> "$WORK/mcrl.log" 2>&1 &
      echo "started the mcrl sweep (log $WORK/mcrl.log)"
      [ -f "$WORK/mcrl/provenance.json" ] || write_provenance "$WORK/mcrl" "$COMMIT" \
        "mcrl sweep --file docs/studies/sac-baseline/early/sweep.yaml --workers ${WORKERS:-1} --threads-per-run 1 --exp EXP" \
        "git checkout $COMMIT && mcrl train --preset fetchpush-sac --steps 20000 --set squash_correction=exact --seed N  (or epsilon)"
    fi
    if pgrep -f "parity_sb3.py sb3 .*--run-dir $WORK/sb3/" > /dev/null; then echo "sb3 chain already running"; else
      (trap '' HUP; for s in ${SB3_SEEDS:-0 1 2 3 4 5}; do
         d="$WORK/sb3/runs/sb3-sac-s$s"
         [ -f "$d/done" ] && continue
         if ls "$d"/sb3_checkpoints/step_*/state.pkl > /dev/null 2>&1; then args=(--resume)
         else args=(--preset fetchpush-sac --steps 20000 --seed "$s" --overwrite); fi
         OMP_NUM_THREADS=1 "$CODE/.venv/bin/python" "$CODE/benchmarks/parity_sb3.py" sb3 "${args[@]}" --threads 1 \
           --run-dir "$d" --no-progress
       done) >> "$WORK/sb3.log" 2>&1 &
      echo "started the stable-baselines3 chain (log $WORK/sb3.log)"
      [ -f "$WORK/sb3/provenance.json" ] || printf '{"commit": "%s", "machine": "%s", "command": "%s"}\n' "$COMMIT" \
        "$(machine_name)" "python benchmarks/parity_sb3.py sb3 --preset fetchpush-sac --steps 20000 --seed N --threads 1 --run-dir DIR" \
        > "$WORK/sb3/provenance.json"
    fi ;;
  *) echo "usage: $0 start|stop|sync|status|table" >&2; exit 2 ;;
esac
