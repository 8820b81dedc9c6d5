"""A run directory as the sweep driver sees it: where it lies in ``EXP``, how far it got, and its files
in transit.

A Ray worker that cannot see ``EXP`` (no shared filesystem) trains in a temporary directory and sends
the run's files to the driver (``collect_run_files``), which writes them into ``EXP/runs/<name>/``
the way the trainer would (``write_run_files``), so that a resumed or reported run cannot tell the
difference. File names are ``mcrl.run.rundir``'s; a checkpoint is installed by ``mcrl.run.checkpoint.install``,
as a run installs its own.
"""
from __future__ import annotations

import os
from pathlib import Path

from mcrl.errors import MCRLError
from mcrl.files import write_atomic
from mcrl.run import checkpoint, rundir

RUNS = rundir.RUNS
_LATEST_KEY = f"{rundir.CHECKPOINTS}/{rundir.LATEST}"  # the `latest` pointer among the shipped files


def run_dir(exp: Path, name: str) -> Path:
    return exp / RUNS / name


def run_status(run_dir: Path) -> tuple[str, int]:
    """("finished" | "checkpoint" | "new", newest step known)."""
    if rundir.is_done(run_dir):
        try:
            return "finished", int(rundir.read_json(run_dir / rundir.DONE).get("step", 0))
        except (TypeError, ValueError):
            return "finished", 0
    latest = rundir.latest_checkpoint(run_dir)
    if latest is not None:
        return "checkpoint", rundir.checkpoint_step(latest) or 0
    return "new", 0


def last_logged_step(run_dir: Path) -> int:
    """The step of the last complete row of metrics.csv (0 if none).

    Reads only the file's tail (not rundir.read_rows): the driver polls every running run each second."""
    path = run_dir / rundir.METRICS
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - 4096))
            tail = f.read().decode("utf-8", "replace")
    except OSError:
        return 0
    lines = tail.split("\n")[:-1]  # complete lines only
    for line in reversed(lines):
        head = line.split(",", 1)[0]
        try:
            return int(float(head))
        except ValueError:
            continue
    return 0


def _complete_lines(data: bytes) -> bytes:
    """A CSV that may be appended to right now: up to its last newline."""
    i = data.rfind(b"\n")
    return data[: i + 1] if i >= 0 else b""


def collect_run_files(run_dir: Path, final: bool) -> dict[str, bytes]:
    """The run's files to send to the driver: every file outside checkpoints/ (CSVs cut to complete
    rows unless `final`), plus the newest checkpoint and the `latest` pointer; `done` only if `final`."""
    files: dict[str, bytes] = {}
    for p in sorted(run_dir.rglob("*")):
        rel = p.relative_to(run_dir)
        if not p.is_file() or rel.parts[0] == rundir.CHECKPOINTS or p.name.startswith("."):
            continue
        if rel.as_posix() == rundir.DONE and not final:
            continue
        data = p.read_bytes()
        files[rel.as_posix()] = data if final or p.suffix != ".csv" else _complete_lines(data)
    name = rundir.latest_checkpoint(run_dir)
    if name is not None:
        ck = rundir.checkpoint_root(run_dir) / name
        for p in sorted(ck.iterdir()):
            if p.is_file():
                files[f"{rundir.CHECKPOINTS}/{name}/{p.name}"] = p.read_bytes()
        files[_LATEST_KEY] = (name + "\n").encode()
    return files


def write_run_files(run_dir: Path, files: dict[str, bytes], keep: int) -> None:
    """Write files sent by a worker into `run_dir` the way the trainer would: the other files first, then the
    checkpoint installed (so `latest` never names a step the CSVs have not reached), `done` last."""
    run_dir.mkdir(parents=True, exist_ok=True)
    ck_name = files.get(_LATEST_KEY, b"").decode().strip()
    step = rundir.checkpoint_step(ck_name) if ck_name else None
    if ck_name and step is None:
        raise MCRLError(f"a worker sent a checkpoint named {ck_name!r}: not a checkpoint directory")
    for rel, data in files.items():
        if rel.startswith(f"{rundir.CHECKPOINTS}/") or rel == rundir.DONE:
            continue
        target = run_dir / rel
        if ".." in Path(rel).parts or Path(rel).is_absolute():
            raise MCRLError(f"a worker sent a file outside its run directory ({rel!r})")
        target.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(target, data)
    if step is not None and (rundir.checkpoint_root(run_dir) / ck_name).is_dir():
        rundir.write_latest(run_dir, ck_name)  # sent before: installed already
    elif step is not None:
        prefix = f"{rundir.CHECKPOINTS}/{ck_name}/"

        def write(d: Path) -> None:
            for rel, data in files.items():
                if rel.startswith(prefix):
                    (d / Path(rel).name).write_bytes(data)

        checkpoint.install(run_dir, step, write, keep)
    if rundir.DONE in files:  # last: a run with `done` is finished, whoever reads it
        write_atomic(run_dir / rundir.DONE, files[rundir.DONE])
