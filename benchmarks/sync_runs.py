"""Copy the small files of every finished run of an experiment into a directory that is committed.

    python benchmarks/sync_runs.py SRC_EXP DEST_EXP

For each `SRC_EXP/runs/<name>/` with a `done` marker: config.json, metrics.csv, eval.csv, final_eval.json,
peer.json and done go to `DEST_EXP/runs/<name>/` (never checkpoints, buffers or TensorBoard events);
sweep.json and provenance.json are copied too. Prints the runs it copied. Long experiments run elsewhere
(a clone of a fixed commit); this keeps what they finished safe in git as they go.
"""
from __future__ import annotations

import shutil
import sys
from pathlib import Path

SMALL = ("config.json", "metrics.csv", "eval.csv", "final_eval.json", "peer.json", "done")


def sync(src: Path, dest: Path) -> list[str]:
    copied = []
    dest.mkdir(parents=True, exist_ok=True)
    for name in ("sweep.json", "provenance.json"):
        if (src / name).is_file():
            shutil.copy2(src / name, dest / name)
    runs = src / "runs" if (src / "runs").is_dir() else src
    for run in sorted(p for p in runs.iterdir() if (p / "done").is_file()):
        out = dest / "runs" / run.name
        out.mkdir(parents=True, exist_ok=True)
        for f in SMALL:
            if (run / f).is_file() and ((out / f).read_bytes() if (out / f).is_file() else None) != (run / f).read_bytes():
                shutil.copy2(run / f, out / f)
                copied.append(f"{run.name}/{f}")
    return copied


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    for line in sync(Path(sys.argv[1]), Path(sys.argv[2])):
        print(line)
