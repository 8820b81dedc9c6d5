"""The figures of the GPU measurement, read off the runs' own metrics.csv and eval.csv (standard library only).

A throughput phase trains real runs through mcrl's loop with log rows every `log_every` steps and evaluations of
`eval_episodes` episodes every `eval_every` steps. Its rows give, without instrumenting the loop:

- compile time: the first learning interval (learning_starts, learning_starts + log_every] holds the first
  compilation of acting and of the (vmapped) gradient step; its time less that interval's steps at the steady
  rate;
- steady-state steps/s: steps over seconds of the later intervals that hold no evaluation (group steps: each
  advances every run of the group once);
- evaluation cost: the time an evaluation interval takes beyond the steady rate, per member and episode (the
  first evaluation compiles the deterministic policy and is reported apart).

The equivalence check compares two runs' metrics.csv value by value (every learning column, not the timings),
and the projections turn the measured group rates into the wall time of the thesis' tables.
"""
from __future__ import annotations

import math
import statistics
from typing import Any

Row = dict[str, Any]
TIMING = ("time_s", "steps_per_s")


def _intervals(rows: list[Row]) -> list[tuple[int, int, float]]:
    """(first step exclusive, last step inclusive, seconds) between consecutive log rows; the first row's interval
    starts at step 0, time 0 (the loop's start)."""
    out, prev_step, prev_t = [], 0, 0.0
    for r in rows:
        step, t = int(r["step"]), float(r["time_s"])
        out.append((prev_step, step, t - prev_t))
        prev_step, prev_t = step, t
    return out


def throughput(rows: list[Row], evals: list[Row], learning_starts: int, members: int) -> dict[str, Any]:
    """Compile time, steady-state group steps/s and evaluation cost of one phase (see the module's docstring).
    Figures that the rows cannot give (too short a window) are None, with the reason in `missing`."""
    eval_steps = sorted(int(e["step"]) for e in evals)
    ivs = _intervals(rows)
    first_learning = next((i for i, (a, b, _) in enumerate(ivs) if a <= learning_starts < b), None)
    has_eval = [any(a < s <= b for s in eval_steps) for a, b, _ in ivs]
    steady = [iv for i, iv in enumerate(ivs)
              if first_learning is not None and i > first_learning and not has_eval[i] and iv[2] > 0]
    out: dict[str, Any] = {"members": members, "rows": len(rows), "last_step": int(rows[-1]["step"]) if rows else 0,
                           "steady_intervals": len(steady), "missing": []}
    rate = None
    if len(steady) >= 2:
        steps, secs = sum(b - a for a, b, _ in steady), sum(t for _, _, t in steady)
        rate = steps / secs
        out.update(window_steps=steps, window_s=round(secs, 3),
                   median_interval_steps_per_s=statistics.median((b - a) / t for a, b, t in steady))
    else:
        out["missing"].append("fewer than 2 steady log intervals after the first learning interval")
    out["steady_steps_per_s"] = rate  # group steps/s
    out["run_steps_per_s"] = None if rate is None else rate * members  # every member's steps together
    compile_s = None
    if first_learning is not None and rate is not None:
        a, b, t = ivs[first_learning]
        pre = [iv for iv in ivs[:first_learning] if iv[2] > 0]
        random_rate = sum(y - x for x, y, _ in pre) / sum(s for _, _, s in pre) if pre else None
        random_steps = learning_starts - a
        expected = (b - learning_starts) / rate + (random_steps / random_rate if random_rate else 0.0)
        compile_s = max(t - expected, 0.0)
        out["random_steps_per_s"] = random_rate
    else:
        out["missing"].append("no first learning interval with a steady rate to compare")
    out["compile_s"] = compile_s
    episodes = {int(e["step"]): int(e["episodes"]) for e in evals}
    extra = [(t - (b - a) / rate, episodes[s]) for (a, b, t), ev in zip(ivs, has_eval) if ev and rate
             for s in [next(x for x in eval_steps if a < x <= b)]]
    out["eval_rounds"] = len(extra)
    out["first_eval_s"] = extra[0][0] if extra else None  # includes compiling the deterministic policy
    later = [x / (members * n) for x, n in extra[1:]]
    per = statistics.median(later) if later else None
    out["eval_s_per_member_episode"] = per
    if per is None:
        out["missing"].append("fewer than 2 evaluations in the window (the first one compiles)")
    return out


def block_means(rows: list[Row], columns: list[str], after: int, block: int) -> list[Row]:
    """Means of `columns` over blocks of `block` steps after step `after` (rows logged every step), one row per
    block, keyed by its last step; a column empty in a block stays None."""
    out: dict[int, dict[str, list[float]]] = {}
    for r in rows:
        if r["step"] > after:
            end = after + block * -(-(int(r["step"]) - after) // block)
            for c in columns:
                if r.get(c) is not None:
                    out.setdefault(end, {}).setdefault(c, []).append(r[c])
    return [{"step": end, **{c: (sum(v[c]) / len(v[c]) if c in v else None) for c in columns}}
            for end, v in sorted(out.items())]


def compare(a: list[Row], b: list[Row], rtol: float, atol: float, columns: list[str] | None = None) -> dict[str, Any]:
    """Every learning column of two runs' metrics.csv, row by row: |x - y| <= atol + rtol * max(|x|, |y|).
    The result names the worst value (largest |x - y| / max(|x|, |y|, atol)) and whether all passed."""
    if not a or not b:
        return {"passed": False, "reason": "a run has no rows", "rows": 0}
    cols = columns or [k for k in a[0] if k not in TIMING]
    steps_a, steps_b = [r["step"] for r in a], [r["step"] for r in b]
    if steps_a != steps_b:
        return {"passed": False, "reason": f"different log steps {steps_a} / {steps_b}", "rows": 0}
    worst, failures, n = None, 0, 0
    for ra, rb in zip(a, b):
        for c in cols:
            x, y = ra.get(c), rb.get(c)
            if x is None and y is None:
                continue
            n += 1
            if x is None or y is None or math.isnan(x) != math.isnan(y):
                failures += 1
                worst = {"column": c, "step": ra["step"], "a": x, "b": y, "rel": math.inf}
                continue
            if math.isnan(x):
                continue
            d = abs(x - y)
            rel = d / max(abs(x), abs(y), atol)
            if d > atol + rtol * max(abs(x), abs(y)):
                failures += 1
            if worst is None or rel > worst["rel"]:
                worst = {"column": c, "step": ra["step"], "a": x, "b": y, "rel": rel}
    return {"passed": failures == 0, "rtol": rtol, "atol": atol, "rows": len(a), "values": n, "failures": failures,
            "max_rel": None if worst is None else worst["rel"], "worst": worst,
            "bit_identical": all(ra.get(c) == rb.get(c) for ra, rb in zip(a, b) for c in cols)}


def project(name: str, sets: list[int], steps: int, eval_every: int, eval_episodes: int, final_episodes: int,
            figures: dict[str, Any], measured: int) -> dict[str, Any]:
    """Wall time of a table whose runs fall into `sets` of runs that can share a group, each set trained as vmapped
    groups of at most the `measured` group's size, one group after another on one GPU. Each group runs at the
    measured steady group rate (a smaller group is assumed no slower per group step), compiles once, and evaluates
    its members one after another at the measured cost per member and episode: every `eval_every` steps
    `eval_episodes` episodes, and `final_episodes` at the end. Checkpoint writes are not counted. A part that a
    figure is missing for is None, and so is the total."""
    groups = [min(measured, n - i) for n in sets for i in range(0, n, max(measured, 1))]
    rate, compile_s = figures.get("steady_steps_per_s"), figures.get("compile_s")
    per_episode = figures.get("eval_s_per_member_episode")
    out: dict[str, Any] = {"table": name, "runs": sum(sets), "steps_per_run": steps, "groups": groups,
                           "assumption": "groups one after another on one GPU, each at the measured group's steady "
                                         "rate (groups no larger than it); checkpoints not counted"}
    if rate is None or not measured:
        out.update(train_h=None, compile_h=None, eval_h=None, total_h=None, reason="no steady group rate measured")
        return out
    episodes = ((steps - 1) // eval_every) * eval_episodes + final_episodes if eval_every else final_episodes
    out["eval_episodes_per_run"] = episodes
    out["train_h"] = len(groups) * steps / rate / 3600
    out["compile_h"] = None if compile_s is None else len(groups) * compile_s / 3600
    out["eval_h"] = None if per_episode is None else sum(groups) * episodes * per_episode / 3600
    parts = (out["train_h"], out["compile_h"], out["eval_h"])
    out["total_h"] = None if None in parts else sum(parts)
    return out
