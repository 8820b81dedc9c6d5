#!/usr/bin/env bash
# The GPU path, measured (issue 51): one command on a lent GPU machine writes one JSON to $OUT.
#
#   bash benchmarks/gpu/run.sh fetch-wheels       # here, before the GPU call: wheels + the commit they go with
#   bash benchmarks/gpu/run.sh gpu                # there: install from the carried wheels, measure (<= 9 min)
#   bash benchmarks/gpu/run.sh dry-run [OUTDIR]   # here: the same measurement on the CPU at tiny sizes
#
# The `run` tool invocation (the device tool; its machine has no network, so everything travels):
#   command:   bash benchmarks/gpu/run.sh gpu
#   carry:     ["benchmarks/gpu/wheels"]
#   timeout_s: 590   (the script ends itself by GPU_TOTAL_S=540 s: install, then measure.py's phases, each
#                     stopped at its share of what is left; the JSON is rewritten after every phase)
# Before it: commit, then `bash benchmarks/gpu/run.sh fetch-wheels` (it records HEAD in wheels/commit.txt).
# A shorter second window: GPU_TOTAL_S=250 GPU_ONLY=fetchpush_single bash benchmarks/gpu/run.sh gpu (the
# equivalence check, then only the phases named; no projections).
# After it: the tool's files_at holds gpu.json, install.log and measure.log; give the machine back.
#
# The image has Python 3.12, jax 0.11 with CUDA 13, flax, optax, numpy, scipy, pandas, matplotlib, tensorboard,
# yaml and tqdm, and lacks MuJoCo, gymnasium, gymnasium-robotics and their few pure-Python needs. Those travel as
# wheels (WHEELS below, versions from constraints.txt) and are installed with --no-deps into a folder of their own
# on PYTHONPATH, beside mcrl's src/ (equivalent to `pip install --no-deps -e .`): nothing of the image's
# jax/flax/optax/numpy is replaced.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPO=$PWD
HERE=benchmarks/gpu
WHEEL_DIR=$HERE/wheels
# what mcrl imports (training, env workers) that the image lacks: found by importing mcrl's training path
WHEELS="mujoco gymnasium gymnasium-robotics Farama-Notifications pettingzoo tensorboardX glfw"
START=$(date +%s)

python_here() { if [ -x .venv/bin/python ]; then echo .venv/bin/python; else echo python3; fi; }

fetch_wheels() {
    local py pins=()
    py=${PY:-$(python_here)}
    for name in $WHEELS; do
        pins+=("$(grep -i -E "^${name}==" constraints.txt)")
    done
    mkdir -p "$WHEEL_DIR"
    "$py" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d "$WHEEL_DIR" "${pins[@]}"
    echo "$(git rev-parse HEAD) dirty_files=$(git status --porcelain -- src benchmarks/gpu | wc -l)" > "$WHEEL_DIR/commit.txt"
    ls -l "$WHEEL_DIR"
    echo "pins: ${pins[*]}"
    echo "wheels: $(du -cb "$WHEEL_DIR"/*.whl | tail -1 | cut -f1) bytes; tracked tree: $(git ls-files -z | xargs -0 du -cb | tail -1 | cut -f1) bytes"
}

install() {  # $1: python, $2: site folder, $3: work folder; writes $3/install.json
    local py=$1 site=$2 work=$3 t0 rc=0
    t0=$(date +%s)
    rm -rf "$site"
    "$py" -m pip install --no-index --no-deps --no-compile --no-cache-dir --target "$site" "$WHEEL_DIR"/*.whl \
        > "$work/install.log" 2>&1 || rc=$?
    export PYTHONPATH="$site:$REPO/src${PYTHONPATH:+:$PYTHONPATH}"
    "$py" - "$work/install.json" "$rc" "$(( $(date +%s) - t0 ))" "$WHEEL_DIR" "$work/install.log" <<'EOF'
import json, os, subprocess, sys
from pathlib import Path
out, rc, secs, wheels, log = sys.argv[1:]
size = lambda p: sum(f.stat().st_size for f in Path(p).rglob("*") if f.is_file() and ".git" not in f.parts)
where = subprocess.run([sys.executable, "-c", "import jax, mcrl, mujoco; print(jax.__file__, mcrl.__file__, mujoco.__file__)"],
                       capture_output=True, text=True)
json.dump({"install": {"rc": int(rc), "seconds": int(secs), "log_tail": Path(log).read_text()[-2000:],
                       "wheels": {w.name: w.stat().st_size for w in sorted(Path(wheels).glob("*.whl"))},
                       "wheels_bytes": size(wheels), "tree_bytes_arrived": size("."),
                       "imports_from": where.stdout.strip() or where.stderr.strip()[-500:]}}, open(out, "w"), indent=1)
EOF
}

mode=${1:-gpu}
case "$mode" in
fetch-wheels)
    fetch_wheels ;;
gpu)
    OUT=${OUT:?the device tool sets OUT}
    unset MUJOCO_GL PYOPENGL_PLATFORM  # no rendering: MuJoCo's EGL path would want PyOpenGL, which is not carried
    WORK=$(mktemp -d /tmp/mcrl-gpu.XXXXXX)
    PY=${PY:-python3}
    install "$PY" /tmp/mcrl-site "$WORK"
    cp "$WORK/install.log" "$OUT/install.log"
    budget=$(( ${GPU_TOTAL_S:-540} - ($(date +%s) - START) - 25 ))  # 25 s: the last phase's stop and the JSON
    set +e
    PYTHONUNBUFFERED=1 "$PY" $HERE/measure.py --out "$OUT/gpu.json" --budget-s "$budget" --work "$WORK" \
        --extra "$WORK/install.json" \
        ${GPU_ONLY:+--only "$GPU_ONLY"} 2>&1 | tee "$OUT/measure.log"
    rc=${PIPESTATUS[0]}
    echo "run.sh: exit $rc after $(( $(date +%s) - START )) s"
    exit "$rc" ;;
dry-run)
    OUTDIR=${2:-/tmp/mcrl-gpu-dry-run}
    mkdir -p "$OUTDIR"
    PY=${PY:-$(python_here)}
    export PYTHONPATH="$REPO/src${PYTHONPATH:+:$PYTHONPATH}"  # this checkout's mcrl, as on the GPU machine
    extra=()
    if [ "${INSTALL:-0}" = 1 ]; then  # rehearse the install too (PY: a Python 3.12 without MuJoCo & co.)
        install "$PY" "$OUTDIR/site" "$OUTDIR"
        extra=(--extra "$OUTDIR/install.json")
    fi
    "$PY" $HERE/measure.py --dry-run --out "$OUTDIR/gpu-dry-run.json" --work "$OUTDIR/work" "${extra[@]}" ;;
*)
    echo "usage: bash benchmarks/gpu/run.sh fetch-wheels | gpu | dry-run [OUTDIR]" >&2
    exit 2 ;;
esac
