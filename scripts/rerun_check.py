"""Compare a short re-run of a committed run with the committed rows: does a re-run give the same numbers?

    python scripts/rerun_check.py COMMITTED_RUN RERUN_RUN [--machine TEXT] [--out FILE.json]

Every metrics.csv and eval.csv row of the re-run (made with the same commit and config, usually with a smaller
``--steps``) is matched by step with the committed run's row, and every column is compared except the wall-clock
ones (time_s, steps_per_s). The re-run's last row is compared only in its training columns: with a smaller
``--steps`` that step is where its final evaluation (more episodes) lands, where the committed run made a regular
one. Prints the rows compared, how many are identical, and per column the largest difference and the first step
where it differs; ``--out`` writes the same as JSON. Exit 0 when every compared value is identical, 1 otherwise.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

WALL_CLOCK = ("time_s", "steps_per_s")
EVAL_COLUMNS_IN_METRICS = ("eval_success_rate", "eval_mean_return")


def _rows(path: Path) -> dict[int, dict[str, str]]:
    with path.open(newline="") as f:
        return {int(float(r["step"])): r for r in csv.DictReader(f)}


def _value(text: str) -> float | None:
    return None if text in ("", None) else float(text)


def compare(committed: Path, rerun: Path) -> dict:
    out: dict = {"committed": str(committed), "rerun": str(rerun), "files": {}}
    for name in ("metrics.csv", "eval.csv"):
        a, b = _rows(committed / name), _rows(rerun / name)
        last = max(b) if b else None
        cols: dict[str, dict] = {}
        compared = identical = 0
        for step in sorted(b):
            if step not in a:
                continue
            skip = set(WALL_CLOCK) | ({"success_rate", "mean_return", "episodes", *EVAL_COLUMNS_IN_METRICS}
                                      if step == last else set())
            if name == "eval.csv" and step == last:
                continue  # the re-run's final evaluation, not the committed run's regular one
            same_row = True
            for col in b[step]:
                if col in skip or col == "step":
                    continue
                x, y = _value(a[step].get(col, "")), _value(b[step][col])
                c = cols.setdefault(col, {"max_abs_diff": 0.0, "first_diff_step": None})
                if x is None and y is None:
                    continue
                diff = math.inf if (x is None) != (y is None) else abs(x - y)
                if diff > 0:
                    same_row = False
                    c["max_abs_diff"] = max(c["max_abs_diff"], diff)
                    c["first_diff_step"] = c["first_diff_step"] or step
            compared += 1
            identical += same_row
        out["files"][name] = {"rows_compared": compared, "rows_identical": identical, "last_step": last,
                              "columns": {k: v for k, v in cols.items() if v["first_diff_step"] is not None}}
    out["identical"] = all(f["rows_compared"] > 0 and f["rows_identical"] == f["rows_compared"]
                           for f in out["files"].values())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("committed", type=Path)
    ap.add_argument("rerun", type=Path)
    ap.add_argument("--machine", help="the machine the re-run ran on (recorded in the JSON)")
    ap.add_argument("--note", help="free text recorded in the JSON (e.g. the command)")
    ap.add_argument("--out", type=Path)
    a = ap.parse_args(argv)
    for d in (a.committed, a.rerun):
        if not (d / "metrics.csv").is_file():
            print(f"rerun_check: error: {d} has no metrics.csv: give two run directories", file=sys.stderr)
            return 2
    res = compare(a.committed, a.rerun)
    res.update({k: v for k, v in (("machine", a.machine), ("note", a.note)) if v})
    for name, f in res["files"].items():
        print(f"{name}: {f['rows_identical']} of {f['rows_compared']} rows identical (up to step {f['last_step']})")
        for col, c in f["columns"].items():
            print(f"  {col}: max |diff| {c['max_abs_diff']:.3g}, first at step {c['first_diff_step']}")
    print("identical" if res["identical"] else "DIFFERENT")
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(res, indent=1) + "\n")
    return 0 if res["identical"] else 1


if __name__ == "__main__":
    sys.exit(main())
