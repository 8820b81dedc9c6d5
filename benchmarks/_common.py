"""What the benchmark scripts share. Importing it puts this checkout's ``src/`` on ``sys.path`` when mcrl is
not installed (without importing mcrl, so jax and torch load later, after any thread limits). The standard
library only."""
from __future__ import annotations

import importlib.util
import json
import os
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent

if importlib.util.find_spec("mcrl") is None and (REPO_ROOT / "src" / "mcrl").is_dir():
    sys.path.insert(0, str(REPO_ROOT / "src"))

def usable_cores() -> int:
    """The cores this process may run on (its affinity mask where there is one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def cpuinfo() -> dict[str, str]:
    """The first processor's fields in /proc/cpuinfo ("model name", "cpu family", "model", "flags", ...); {}
    where there is none."""
    out: dict[str, str] = {}
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return out
    for line in lines:
        if not line.strip():
            if out:
                break
            continue
        key, _, value = line.partition(":")
        out.setdefault(key.strip(), value.strip())
    return out


def cpu_label() -> str | None:
    """"<model name> (family F model M)", the CPU as the docs name machines; None where unknown."""
    info = cpuinfo()
    if not all(k in info for k in ("model name", "cpu family", "model")):
        return None
    return f"{info['model name']} (family {info['cpu family']} model {info['model']})"


def log(msg: str) -> None:
    """Progress on stderr (stdout holds the results)."""
    print(msg, file=sys.stderr, flush=True)


def write_json(path: Path | str, obj, indent: int = 2, default=None) -> None:
    """`obj` as JSON, one trailing newline, creating the parent directory."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=indent, default=default) + "\n")


def md_row(cells) -> str:
    """One Markdown table row."""
    return "| " + " | ".join(str(c) for c in cells) + " |"


def md_head(cols, align: str = "---") -> list[str]:
    """A Markdown table's header row and separator (`align` "---:" right-aligns every column)."""
    return [md_row(cols), "|" + f" {align} |" * len(cols)]
