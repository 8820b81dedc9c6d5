"""``EXP/provenance.json``: who ran each sweep call into an experiment directory, with what code, where and when.

`run_sweep` appends one entry per call to the file's ``"sweeps"`` list once it holds ``EXP``'s lock, and writes its
end time when the call returns or fails, so a sweep killed outright keeps an entry whose ``"ended"`` is null::

    {"sweeps": [{"command": "mcrl sweep --preset fetchreach-sac --alphas 0,0.2 --seeds 2 --exp exp/local",
                 "mcrl": "0.2.0", "commit": "5c418ac...", "dirty": false,
                 "machine": "AMD EPYC 9R14, family 25 model 17, 2 cores", "host": "box",
                 "started": "2026-12-03T10:00:00+00:00", "ended": "2026-12-03T10:20:41+00:00"}, ...]}

Every other key of the file (the hand-written ``commit``, ``machine``, ``command`` of the committed experiments) is
kept as it is, and so is every earlier entry: a repeated sweep call adds to the record, never replaces it. The
report shows both (`mcrl.analysis.provenance`). ``commit`` is present only when mcrl runs from a git checkout of
itself (an editable install); ``machine`` is the driver's, where the sweep was started (Ray runs may be elsewhere).
"""
from __future__ import annotations

import json
import os
import platform
import subprocess
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from mcrl.errors import MCRLError
from mcrl.files import write_json
from mcrl.run.rundir import PROVENANCE

SWEEPS = "sweeps"  # the key of the list of sweep calls


def now() -> str:
    """The local time with its offset, to the second: '2026-12-03T10:00:00+01:00'."""
    return datetime.now(timezone.utc).astimezone().isoformat(timespec="seconds")


def machine() -> str:
    """The CPU as the committed experiments name machines: 'model name, family F model M, N cores'."""
    try:
        fields = dict(ln.split(":", 1) for ln in Path("/proc/cpuinfo").read_text().split("\n\n")[0].splitlines()
                      if ":" in ln)
        fields = {k.strip(): v.strip() for k, v in fields.items()}
        cpu = f"{fields['model name']}, family {fields['cpu family']} model {fields['model']}"
    except (OSError, KeyError):  # not Linux, or a CPU that names itself otherwise
        cpu = platform.processor() or platform.machine() or "unknown CPU"
    return f"{cpu}, {os.cpu_count()} cores"


def code_version() -> dict[str, Any]:
    """mcrl's version, and its git commit (with whether files differ from it) when this mcrl is a git checkout of
    itself: the repository's top level holds this package at src/mcrl (not, say, a project that vendors it)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        out: dict[str, Any] = {"mcrl": version("mcrl")}
    except PackageNotFoundError:
        out = {"mcrl": "unknown"}
    here = Path(__file__).resolve().parents[1]

    def git(*args: str) -> str | None:
        try:
            res = subprocess.run(["git", "-C", str(here), *args], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return res.stdout.strip() if res.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    if top and (Path(top) / "src" / "mcrl").resolve() == here:
        commit, status = git("rev-parse", "HEAD"), git("status", "--porcelain", "--untracked-files=no")
        if commit:
            out["commit"] = commit
            if status is not None:
                out["dirty"] = bool(status)
    return out


def read(exp: Path) -> dict[str, Any]:
    """EXP/provenance.json ({} when there is none); MCRLError when it cannot be extended without losing what it
    holds."""
    path = exp / PROVENANCE
    if not path.exists():
        return {}
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise MCRLError(f"{path} cannot be read ({type(e).__name__}): fix it or move it away; the sweep would "
                        "otherwise overwrite the provenance it holds") from None
    if not isinstance(doc, dict) or not isinstance(doc.get(SWEEPS, []), list):
        raise MCRLError(f"{path} is not a JSON object with a '{SWEEPS}' list: fix it or move it away; the sweep "
                        "would otherwise overwrite the provenance it holds")
    return doc


def _write(exp: Path, doc: dict[str, Any]) -> None:
    write_json(exp / PROVENANCE, doc, indent=1, newline=True)  # indent 1: as the committed experiments' files


def start(exp: Path, command: str) -> int:
    """Add this sweep call to EXP/provenance.json (ended: null); its index in the list. The caller holds EXP's
    lock, so no other sweep writes the file meanwhile."""
    doc = read(exp)
    entry = {"command": command, **code_version(), "machine": machine(), "host": platform.node(),
             "started": now(), "ended": None}
    doc[SWEEPS] = [*doc.get(SWEEPS, []), entry]
    exp.mkdir(parents=True, exist_ok=True)
    _write(exp, doc)
    return len(doc[SWEEPS]) - 1


def end(exp: Path, index: int) -> None:
    """Write the end time of the sweep call `start` returned `index` for."""
    doc = read(exp)
    sweeps = doc.get(SWEEPS, [])
    if index < len(sweeps) and isinstance(sweeps[index], dict):
        sweeps[index]["ended"] = now()
        _write(exp, doc)
