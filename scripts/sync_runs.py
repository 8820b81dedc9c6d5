"""Copy the small files of every finished run of an experiment into a directory that is committed.

    python scripts/sync_runs.py SRC_EXP DEST_EXP [--machine "AMD EPYC, family 25 model 17, 2 cores"]

For each `SRC_EXP/runs/<name>/` with a `done` marker: config.json, metrics.csv, eval.csv, final_eval.json,
peer.json and done go to `DEST_EXP/runs/<name>/` (never checkpoints, buffers or TensorBoard events);
sweep.json is copied too, and provenance.json merged. Prints the runs it copied. Long experiments run elsewhere
(a clone of a fixed commit); this keeps what they finished safe in git as they go.

An experiment can span machines (a new machine resumes the unfinished runs): with --machine, each run copied
here for the first time is recorded as finished on that machine in DEST's provenance.json ("machines": run ->
machine, kept across syncs), and its "machine" names every machine with its runs.
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

SMALL = ("config.json", "metrics.csv", "eval.csv", "final_eval.json", "peer.json", "done")
PROVENANCE = "provenance.json"


def machine_summary(machines: dict[str, str]) -> str:
    """One machine's name, or each machine followed by the runs that finished on it."""
    by_machine: dict[str, list[str]] = {}
    for run, m in sorted(machines.items()):
        by_machine.setdefault(m, []).append(run)
    if len(by_machine) == 1:
        return next(iter(by_machine))
    return "; ".join(f"{m} (runs {', '.join(runs)})" for m, runs in by_machine.items())


def merge_provenance(src: Path, dest: Path, new_runs: list[str], machine: str | None) -> None:
    """DEST's provenance.json: SRC's keys, with DEST's record of which machine finished which run kept."""
    old = json.loads((dest / PROVENANCE).read_text()) if (dest / PROVENANCE).is_file() else {}
    new = json.loads((src / PROVENANCE).read_text()) if (src / PROVENANCE).is_file() else {}
    if not old and not new:
        return
    machines = dict(old.get("machines") or {})
    if machine:
        machines.update({run: machine for run in new_runs if run not in machines})
    merged = {**old, **new}
    if machines:
        merged["machines"] = dict(sorted(machines.items()))
        merged["machine"] = machine_summary(machines)
    (dest / PROVENANCE).write_text(json.dumps(merged, indent=1) + "\n")


def sync(src: Path, dest: Path, machine: str | None = None) -> list[str]:
    copied, new_runs = [], []
    dest.mkdir(parents=True, exist_ok=True)
    if (src / "sweep.json").is_file():
        shutil.copy2(src / "sweep.json", dest / "sweep.json")
    runs = src / "runs" if (src / "runs").is_dir() else src
    for run in sorted(p for p in runs.iterdir() if (p / "done").is_file()):
        out = dest / "runs" / run.name
        if not (out / "done").is_file():
            new_runs.append(run.name)
        out.mkdir(parents=True, exist_ok=True)
        for f in SMALL:
            if (run / f).is_file() and ((out / f).read_bytes() if (out / f).is_file() else None) != (run / f).read_bytes():
                shutil.copy2(run / f, out / f)
                copied.append(f"{run.name}/{f}")
    merge_provenance(src, dest, new_runs, machine)
    return copied


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", type=Path)
    ap.add_argument("dest", type=Path)
    ap.add_argument("--machine", help="the machine the newly finished runs ran on")
    a = ap.parse_args()
    for line in sync(a.src, a.dest, a.machine):
        print(line)
