"""``mcrl decide PLAN``: run a sequential plan batch by batch until its claims are decided.

One call goes round: read ``looks.jsonl`` (refusing a plan changed since its first look); if every claim is decided,
start nothing; otherwise run the next batch (the next ``batch`` seeds of every arm that still has an open claim)
through a sweep backend (`mcrl.sweep.run_sweep`, local, Ray or vmap) into the plan's directory; once every run of
the batch has finished, take the look (`mcrl.decide.look.take_look`) and append its record to ``looks.jsonl``.
A batch that is stopped, killed or has a failed run takes no look: the same command resumes it from its runs'
checkpoints (a sweep's guarantee: at most the work since each run's last checkpoint is lost), and a look is
never taken twice (the directory is locked while ``mcrl decide`` runs on it).

Files, in the plan's directory (``EXP``): ``plan.yaml``, ``looks.jsonl`` (one JSON record per look, appended, never
rewritten), ``sweep.json`` and ``runs/<arm>-s<seed>/`` as `mcrl sweep` writes them.
"""
from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcrl.decide.boundaries import lower_bounds, upper_bounds
from mcrl.decide.look import DECIDED, information, take_look
from mcrl.decide.plan import Plan, load_plan
from mcrl.errors import MCRLError
from mcrl.run import lock as locks
from mcrl.run import rundir
from mcrl.sweep.provenance import code_version, machine

LOOKS = "looks.jsonl"
LOCK = ".decide.lock"


@dataclass
class State:
    plan: Plan
    looks: list[dict]  # the records so far

    @property
    def done(self) -> bool:
        return bool(self.looks) and bool(self.looks[-1].get("done"))

    @property
    def open_arms(self) -> list[str]:
        return list(self.plan.arms) if not self.looks else list(self.looks[-1]["continue_arms"])

    def seeds_of(self, arm: str) -> list[int]:
        """The seeds `arm` has been asked to run so far (its looked-at seeds, and the next batch if it is open)."""
        looked = self.looks[-1]["seeds_per_arm"][arm] if self.looks else 0
        more = self.plan.batch if arm in self.open_arms and not self.done else 0
        return self.plan.seeds[:looked + more]

    def next_batch(self) -> dict[str, list[int]]:
        """The seeds each open arm runs before the next look ({} once decided)."""
        if self.done:
            return {}
        return {a: self.seeds_of(a)[-self.plan.batch:] for a in self.open_arms}


def read_looks(plan: Plan) -> list[dict]:
    """``looks.jsonl``'s records; MCRLError when the plan changed after the first look, or the file is damaged."""
    path = plan.dir / LOOKS
    if not path.exists():
        return []
    text = path.read_text()
    lines = text.split("\n")
    if lines and lines[-1].strip() and not text.endswith("\n"):
        lines = lines[:-1]  # a record cut short by a crash: it was never taken (its batch's runs are all kept)
    looks = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            looks.append(json.loads(line))
        except json.JSONDecodeError:
            raise MCRLError(f"{path} line {i + 1} is not a JSON record: restore the file from git") from None
    for i, r in enumerate(looks):
        if r.get("look") != i + 1:
            raise MCRLError(f"{path}: record {i + 1} says look {r.get('look')}: restore the file from git")
        if r.get("plan_hash") != plan.hash:
            raise MCRLError(f"{plan.path} changed after look {i + 1} (its hash {plan.hash[:19]}... differs from the "
                            f"{r.get('plan_hash', '?')[:19]}... the looks recorded): a sequential plan is fixed at "
                            "its first look; restore it (git checkout) or start a new plan in a new directory")
    return looks


def state(plan: Plan) -> State:
    return State(plan, read_looks(plan))


def _runs_dir(plan: Plan) -> Path:
    return plan.dir / rundir.RUNS


def finals_so_far(st: State) -> tuple[dict[str, list[float]], list[str]]:
    """Each arm's finals over the seeds asked of it so far, and the runs not finished yet."""
    finals: dict[str, list[float]] = {}
    missing = []
    for arm in st.plan.arms:
        finals[arm] = []
        for seed in st.seeds_of(arm):
            name = st.plan.run_name(arm, seed)
            rd = _runs_dir(st.plan) / name
            fe = rundir.read_json(rd / rundir.FINAL_EVAL) if rundir.is_done(rd) else {}
            sr = fe.get("success_rate")
            if sr is None:
                missing.append(name)
            else:
                finals[arm].append(float(sr))
    return finals, missing


def code_commit() -> str | None:
    """The git commit of the mcrl code running (a git checkout of itself), None otherwise."""
    return code_version().get("commit")


def check_commit(plan: Plan, any_commit: bool = False) -> str | None:
    """The running code's commit; MCRLError when the plan pins another one (unless ``any_commit``)."""
    have = code_commit()
    if plan.commit and not any_commit and (have is None or not have.startswith(plan.commit)):
        raise MCRLError(f"{plan.path} pins commit {plan.commit[:12]} but this mcrl is "
                        f"{'not a git checkout' if have is None else have[:12]}: run the plan with that commit's "
                        "mcrl installed apart (see the plan's run.sh), or pass --any-commit to override")
    return have


def append_look(plan: Plan, record: dict) -> None:
    """One line, written with one call on an O_APPEND descriptor and synced: a crash leaves the whole line or a
    cut one, which `read_looks` ignores (the look is then taken again from the same finished runs)."""
    line = (json.dumps(record, sort_keys=False) + "\n").encode()
    fd = os.open(plan.dir / LOOKS, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        path = plan.dir / LOOKS
        if os.fstat(fd).st_size and not path.read_bytes().endswith(b"\n"):  # drop a record cut short by a crash
            os.ftruncate(fd, path.read_bytes().rfind(b"\n") + 1)
        os.write(fd, line)
        os.fsync(fd)
    finally:
        os.close(fd)


def look(plan: Plan, commit: str | None = None) -> dict:
    """Take the next look now; MCRLError while a run of its batch is unfinished, or when the plan is decided."""
    st = state(plan)
    if st.done:
        raise MCRLError(f"{plan.dir} is decided at look {len(st.looks)} ({st.looks[-1]['decision']}): "
                        "no look is left to take")
    finals, missing = finals_so_far(st)
    if missing:
        raise MCRLError(f"look {len(st.looks) + 1} needs every run of its batch finished; {len(missing)} are not "
                        f"({', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''}): run `mcrl decide "
                        f"{plan.path}` to finish them")
    record = take_look(plan, finals, st.looks)
    record.update(seeds={a: st.seeds_of(a) for a in plan.arms}, time=time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                  machine=machine(), mcrl_commit=commit if commit is not None else code_commit())
    append_look(plan, record)
    return record


def batch_plan(st: State):
    """The next batch as a `mcrl.sweep.SweepPlan` (each run validated with `resolve_config`)."""
    from mcrl.config import resolve_config
    from mcrl.sweep.plan import RunPlan, SweepPlan, preflight

    plan = st.plan
    runs = []
    arms = list(st.next_batch())
    # seed-major (every arm's first seed, then every arm's second ...): arms share machines and times alike, so a
    # change of CPU between sessions (XLA's float results differ between CPUs) cannot fall on one arm
    for i in range(len(st.seeds_of(arms[0])) if arms else 0):
        for arm in arms:  # earlier seeds too: finished ones are skipped, a stopped one resumes
            seed = st.seeds_of(arm)[i]
            ov = plan.overrides(arm, seed)
            try:
                cfg = resolve_config(plan.preset, ov)
            except MCRLError as e:
                raise MCRLError(f"{plan.path}: arm {arm}: {e}") from None
            runs.append(RunPlan(plan.run_name(arm, seed), arm, seed, ov, cfg))
    grid: dict[str, list] = {}
    for ov in plan.arms.values():
        for k, v in ov.items():
            if v not in grid.setdefault(k, []):
                grid[k].append(v)
    grid["seed"] = sorted({r.seed for r in runs})
    preflight(runs)
    return SweepPlan(plan.preset, grid, dict(plan.fixed), runs, source="file")


def boundary_table(plan: Plan) -> list[dict[str, Any]]:
    """Each claim's planned bounds at every look (at its own level, and at the family's level once another claim is
    confirmed), if it runs to the maximum with batches as planned."""
    rows = []
    info_max = information(plan.max_seeds, plan.max_seeds)
    for c in plan.claims:
        ns = [plan.batch * (k + 1) for k in range(plan.max_looks)]
        infos = [information(n, n) for n in ns]
        levels = [c.level] + ([plan.level] if plan.multiplicity == "holm" and c.level < plan.level else [])
        for level in levels:
            upper, spent = upper_bounds(infos, info_max, level, c.spending, c.rho)
            lower = (lower_bounds(infos, info_max, upper, c.futility.beta, c.futility.theta, c.futility.spending,
                                  c.futility.rho) if c.futility else [None] * len(ns))
            for k, n in enumerate(ns):
                rows.append({"claim": c.name, "level": level, "look": k + 1, "seeds_per_arm": n,
                             "information_fraction": infos[k] / info_max, "alpha_spent": float(spent[k]),
                             "upper": float(upper[k]), "lower": None if lower[k] is None else float(lower[k])})
    return rows


def format_boundary_table(plan: Plan) -> str:
    lines = ["claim | level | look | seeds an arm | information | alpha spent | efficacy z >= | futility z <=",
             "--- | --- | --- | --- | --- | --- | --- | ---"]
    for r in boundary_table(plan):
        low = "-" if r["lower"] is None or r["lower"] < -30 else f"{r['lower']:.3f}"
        lines.append(f"{r['claim']} | {r['level']:g} | {r['look']} | {r['seeds_per_arm']} | "
                     f"{r['information_fraction']:.3f} | {r['alpha_spent']:.5f} | {r['upper']:.3f} | {low}")
    return "\n".join(lines)


def dry_run(plan: Plan) -> str:
    """What `mcrl decide --dry-run` prints: the plan, its boundary table and the runs the next look needs."""
    st = state(plan)
    lines = [f"plan {plan.path} ({plan.hash[:19]}...): {len(plan.arms)} arms, seeds {plan.seeds[0]}..{plan.seeds[-1]} "
             f"({plan.max_seeds} an arm at most), {plan.batch} an arm per look, family level {plan.level:g} one-sided "
             f"({plan.multiplicity}); {len(st.looks)} look(s) taken", format_boundary_table(plan)]
    if st.done:
        return "\n".join(lines + [f"decided at look {len(st.looks)} ({st.looks[-1]['decision']}): no run would start"])
    todo = batch_plan(st)
    batch = st.next_batch()
    lines += [f"{r.name}  [{r.config_key}, seed {r.seed}]  {r.overrides}" for r in todo.runs
              if r.seed in batch.get(r.config_key, [])]
    lines.append(f"look {len(st.looks) + 1} would need {len(todo.runs)} finished runs; nothing written (--dry-run)")
    return "\n".join(lines)


def summary_line(record: dict) -> str:
    parts = []
    for name, c in record["claims"].items():
        bounds = (f"bounds [{'-inf' if c.get('lower') is None else format(c['lower'], '.3f')}, "
                  f"{'inf' if c.get('upper') is None else format(c['upper'], '.3f')}]")
        at = f" (look {c['decided_at']})" if c.get("decided_at") and c["decided_at"] != record["look"] else ""
        parts.append(f"{name}: z {c['z']:+.3f} {bounds} -> {c['decision']}{at}")
    arms = ", ".join(f"{a} {n}" for a, n in record["seeds_per_arm"].items())
    return f"look {record['look']} (seeds: {arms}): " + "; ".join(parts)


def decide(plan_path: str | Path, *, once: bool = False, any_commit: bool = False,
           out: Callable[[str], None] = print, **sweep_options: Any) -> State:
    """Run `plan_path` until every claim is decided (``once``: at most one batch and its look). Returns the state
    reached; raises MCRLError on a bad plan or settings (before anything is written). A batch that did not finish
    (stopped by a signal, a failed or locked run) takes no look: the returned state has the same looks, and
    `SweepIncomplete` is raised with the sweep's result."""
    from mcrl.sweep import run_sweep

    plan = load_plan(plan_path)
    commit = check_commit(plan, any_commit)
    try:
        held = locks.acquire(plan.dir, LOCK)
    except locks.Locked as e:
        raise MCRLError(f"another `mcrl decide` is running on {plan.dir} ({e.holder}): wait for it or stop it") \
            from None
    try:
        st = state(plan)
        while not st.done:
            batch = st.next_batch()
            finals, missing = finals_so_far(st)
            if missing:
                n = sum(len(s) for s in batch.values())
                out(f"look {len(st.looks) + 1}: running its batch ({n} runs: "
                    + "; ".join(f"{a} seeds {s[0]}-{s[-1]}" for a, s in batch.items()) + f") into {plan.dir}")
                res = run_sweep(batch_plan(st), plan.dir, shared_dir=True, **sweep_options)
                if res.stopped_by is not None or res.failed or res.stopped or res.locked:
                    raise SweepIncomplete(res)
            record = look(plan, commit)
            out(summary_line(record))
            st = state(plan)
            if once:
                break
        if st.done:
            out(f"decided at look {len(st.looks)}: primary claim {st.looks[-1]['primary']}: "
                f"{st.looks[-1]['decision']}")
        return st
    finally:
        held.release()


class SweepIncomplete(MCRLError):
    """A batch's sweep ended before every run finished: no look was taken."""

    def __init__(self, result):
        self.result = result
        what = []
        if result.failed:
            what.append(f"{len(result.failed)} failed ({', '.join(result.failed)})")
        if result.stopped:
            what.append(f"{len(result.stopped)} stopped")
        if result.locked:
            what.append(f"{len(result.locked)} locked by another process")
        super().__init__(f"the batch did not finish ({'; '.join(what) or 'stopped'}): no look taken; the same "
                         "`mcrl decide` command resumes it")


__all__ = ["DECIDED", "LOOKS", "State", "SweepIncomplete", "boundary_table", "decide", "dry_run",
           "format_boundary_table", "look", "read_looks", "state"]
