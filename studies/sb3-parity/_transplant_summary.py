"""``transplant.py summary``: per origin checkpoint and system, each continuation's peak and final mean Q and
entropy coefficient (from its metrics.csv rows), as a Markdown table.

Whether a continuation left the settled band is judged by ``mcrl.analysis.divergence`` when that module exists
(a bound on mean Q from the entropy coefficient, issue 26); without it the column says "no criterion yet" and the
peaks are reported alone.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from _transplant import TransplantError


def _criterion():
    """function(rows, window start, config dict) -> the first step in the window whose mean Q is above
    ``mcrl.analysis.divergence``'s lagged soft-Q bound, 0 if none, None if unknown; None while that module is
    missing. The bound at a row takes the largest coefficient of the preceding lag, so rows before the window
    (the origin run's) count for it."""
    try:
        from mcrl.analysis.divergence import KNOWN_ENVS, lagged_bound, reward_max
    except ImportError:
        return None

    def first_outside(rows: list[dict], start: int, config: dict) -> int | None:
        env = str(config.get("env_id", ""))
        act = next((v[1] for k, v in KNOWN_ENVS.items() if env.startswith(k)), None)
        r_max = reward_max(config)
        rows = sorted((r for r in rows if r.get("q_mean") is not None and r.get("ent_coef") is not None),
                      key=lambda r: r["step"])
        if act is None or r_max is None or not rows:
            return None
        s, q, c = (np.array([r[k] for r in rows], float) for k in ("step", "q_mean", "ent_coef"))
        bound = lagged_bound(s, c, act, float(config.get("gamma", 0.99)), float(config.get("tau", 0.005)), r_max)
        out = (q > bound) & (s > start)
        return int(s[out][0]) if out.any() else 0

    return first_outside


def continuation(run_dir: Path) -> dict:
    """transplant.json plus the peaks and final values of a continuation's metrics.csv."""
    from mcrl.run.rundir import read_rows

    info_path = Path(run_dir) / "transplant.json"
    if not info_path.is_file():
        raise TransplantError(f"{run_dir} has no transplant.json: give directories `transplant.py continue` wrote")
    info = json.loads(info_path.read_text())
    rows = [r for r in read_rows(Path(run_dir) / "metrics.csv") if r.get("q_mean") is not None]
    config = json.loads((Path(run_dir) / "config.json").read_text())
    return {**info, **course(rows), "rows": rows, "config": config, "dir": str(run_dir)}


def course(rows: list[dict]) -> dict:
    if not rows:
        return {"last_step": None}
    q = max(rows, key=lambda r: r["q_mean"])
    e = max(rows, key=lambda r: r["ent_coef"])
    last = rows[-1]
    return {"last_step": int(last["step"]), "first_q": rows[0]["q_mean"], "peak_q": q["q_mean"],
            "peak_q_step": int(q["step"]), "peak_ent": e["ent_coef"], "peak_ent_step": int(e["step"]),
            "final_q": last["q_mean"], "final_ent": last["ent_coef"], "final_critic_loss": last["critic_loss"]}


def _num(x: float | None, signed: bool = True) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    sign = "+" if signed else ""
    if abs(x) >= 100:
        return f"{x:{sign},.0f}"
    return f"{x:{sign}.3g}" if abs(x) >= 1 else f"{x:.3g}"


def table(conts: list[dict], references: dict[str, list[dict]]) -> str:
    """The Markdown tables: one row per continuation (and per origin run given as a reference), then counts."""
    crit = _criterion()
    lines = ["| origin | system | stream | steps done | mean Q, first row | peak mean Q (step) | "
             "peak ent. coef. (step) | final mean Q | final ent. coef. | final critic loss | left the bound at |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    counts = []
    for origin in sorted({c["origin_label"] for c in conts}):
        mine = [c for c in conts if c["origin_label"] == origin]
        start = min(c["origin_step"] for c in mine)
        before = [r for r in references.get(origin, []) if r["step"] <= start]  # the origin's own history
        if origin in references:
            end = start + max(c["steps"] for c in mine)
            rows = [r for r in references[origin] if start < r["step"] <= end and r.get("q_mean") is not None]
            left = crit(before + rows, start, mine[0]["config"]) if crit else None
            lines.append(_row(origin, "its own run", "-", start, course(rows), left))
        for system in ("mcrl", "sb3"):
            members = sorted((c for c in mine if c["system"] == system), key=lambda c: c["stream"])
            lefts = [crit(before + c["rows"], start, c["config"]) if crit else None for c in members]
            lines += [_row(origin, system, c["stream"], c["origin_step"], c, left) for c, left in zip(members, lefts)]
            if members:
                counts.append((origin, system, members, lefts))
    lines += ["", "| origin | system | continuations | left the bound | peak mean Q per continuation |",
              "| --- | --- | --- | --- | --- |"]
    for origin, system, members, lefts in counts:
        gone = ("no criterion yet" if crit is None or any(x is None for x in lefts)
                else f"{sum(x > 0 for x in lefts)} of {len(members)}")
        peaks = ", ".join(_num(c["peak_q"]) for c in members if c["last_step"])
        lines.append(f"| {origin} | {system} | {len(members)} | {gone} | {peaks} |")
    note = ("" if crit is None else "\nLeft the bound: the first step whose mean Q exceeds "
            "`mcrl.analysis.divergence.lagged_bound` (the origin run's rows before the checkpoint count for the "
            "lag when given with --reference); \"no\" = never in these steps.\n")
    return "\n".join(lines) + "\n" + note


def _row(origin, system, stream, start, c: dict, left) -> str:
    if c.get("last_step") is None:
        return f"| {origin} | {system} | {stream} | 0 | - | - | - | - | - | - | - |"
    gone = "no criterion yet" if left is None else ("no" if left == 0 else f"{left // 1000}k")
    return (f"| {origin} | {system} | {stream} | {c['last_step'] - start:,} | {_num(c['first_q'])} | "
            f"{_num(c['peak_q'])} ({c['peak_q_step'] // 1000}k) | {_num(c['peak_ent'], False)} ({c['peak_ent_step'] // 1000}k) | "
            f"{_num(c['final_q'])} | {_num(c['final_ent'], False)} | {_num(c['final_critic_loss'], False)} | {gone} |")


def cmd_summary(args) -> int:
    from mcrl.run.rundir import read_rows

    conts = [continuation(Path(d)) for d in args.dirs]
    refs = {}
    for item in args.reference:
        label, sep, path = item.partition("=")
        if not sep or not (Path(path) / "metrics.csv").is_file():
            raise TransplantError(f"--reference {item!r}: give LABEL=RUN_DIR with RUN_DIR/metrics.csv, LABEL the "
                                  "origin_label of transplant.json (e.g. 'mcrl a0-s8 @ 40k')")
        refs[label] = read_rows(Path(path) / "metrics.csv")
    text = table(conts, refs)
    print(text, end="")
    if args.out:
        Path(args.out).write_text(text)
    return 0
