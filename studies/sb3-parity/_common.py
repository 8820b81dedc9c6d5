"""What the study's scripts share (a frozen copy of what they used of benchmarks/_common.py, so the study does not
move with the maintained benchmarks). Importing it puts this checkout's ``src/`` on ``sys.path`` when mcrl is not
installed (without importing mcrl, so jax and torch load later, after any thread limits). The standard library
only."""
from __future__ import annotations

import importlib.util
import json
import os
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]

if importlib.util.find_spec("mcrl") is None and (REPO_ROOT / "src" / "mcrl").is_dir():
    sys.path.insert(0, str(REPO_ROOT / "src"))

#: One thread for XLA and for torch's OpenMP: for scripts that run beside long experiments. On jax 0.10.2 the
#: XLA flags do not keep XLA to one core (benchmarks/xla_threads.py).
ONE_THREAD = {"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
              "OMP_NUM_THREADS": "1"}


def one_thread() -> None:
    """Limit XLA and torch to one thread each unless the caller's environment says otherwise; call it before
    jax or torch is imported."""
    for k, v in ONE_THREAD.items():
        os.environ.setdefault(k, v)


def cpu_label() -> str | None:
    """"<model name> (family F model M)" of the first processor in /proc/cpuinfo; None where unknown."""
    info: dict[str, str] = {}
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        if not line.strip():
            if info:
                break
            continue
        key, _, value = line.partition(":")
        info.setdefault(key.strip(), value.strip())
    if not all(k in info for k in ("model name", "cpu family", "model")):
        return None
    return f"{info['model name']} (family {info['cpu family']} model {info['model']})"


def write_json(path: Path | str, obj, indent: int = 2, default=None) -> None:
    """`obj` as JSON, one trailing newline, creating the parent directory."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=indent, default=default) + "\n")


def md_row(cells) -> str:
    """One Markdown table row."""
    return "| " + " | ".join(str(c) for c in cells) + " |"


def md_head(cols, align: str = "---") -> list[str]:
    """A Markdown table's header row and separator."""
    return [md_row(cols), "|" + f" {align} |" * len(cols)]
