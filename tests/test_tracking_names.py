"""MLflow gets one name per metric (issue 53): metrics.csv's columns by their names, the evaluations from eval.csv
as eval/success_rate and eval/mean_return, and not metrics.csv's eval_* copies of them beside those."""

from __future__ import annotations

import csv
import re
from pathlib import Path

from mcrl.run.rundir import EVAL_COLUMNS, METRIC_COLUMNS
from mcrl.sweep.tracking import metric_series


def _csv(path: Path, columns: tuple[str, ...], rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns)
        w.writeheader()
        w.writerows(rows)


def test_one_name_per_metric(tmp_path: Path) -> None:
    evals = [{"step": s, "success_rate": s / 1000, "mean_return": -50 + s / 100, "episodes": 10} for s in (0, 500, 1000)]
    _csv(tmp_path / "eval.csv", EVAL_COLUMNS, evals)
    # the loop repeats the last evaluation in metrics.csv's eval_* columns at every log row
    _csv(tmp_path / "metrics.csv", METRIC_COLUMNS,
         [{"step": s, "critic_loss": 1.0 / s, "eval_success_rate": 0.5, "eval_mean_return": -30.0} for s in (200, 400)])
    series = metric_series(tmp_path)
    names = {n for n, _, _ in series}
    assert {"eval/success_rate", "eval/mean_return", "critic_loss"} <= names
    assert not {"eval_success_rate", "eval_mean_return"} & names
    assert [(s, v) for n, v, s in series if n == "eval/success_rate"] == [(e["step"], e["success_rate"]) for e in evals]
    assert [s for n, _, s in series if n == "critic_loss"] == [200, 400]
    # one scheme: no two names that are one metric spelled two ways
    canonical = [re.sub(r"^eval[/_]", "eval.", n) for n in names]
    assert len(canonical) == len(set(canonical))
    # a (name, step) pair is logged once
    assert len({(n, s) for n, _, s in series}) == len(series)
