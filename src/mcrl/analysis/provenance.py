"""The report's last section: how it was made. The statistics it uses, its reference arms and extra directories,
the claims registry, each experiment's provenance.json, and every resume its runs record."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from mcrl.analysis.cells import SEED, code, steps
from mcrl.analysis.experiment import Experiment
from mcrl.analysis.markdown import Block, Bullets, Heading, Paragraph
from mcrl.analysis.runs import Run
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT, bootstrap_backend


def provenance(exp: Experiment, claims_file: str | None) -> list[Block]:
    """How the report was made: statistics used, reference arms, extra directories, claims registry, and each
    experiment's provenance.json."""
    items = [
        f"confidence intervals: 95%, percentile bootstrap over seeds (seed {SEED}), none from fewer than "
        f"{MIN_SEEDS_FOR_VERDICT} seeds; IQM and probability of "
        f"improvement: stratified bootstrap via {bootstrap_backend()}",
        f"readings and verdicts need at least {MIN_SEEDS_FOR_VERDICT} finished seeds in every configuration "
        "compared (MIN_SEEDS_FOR_VERDICT); with fewer the report says 'too few seeds for a verdict'",
        f"claims registry: {code(claims_file) if claims_file else 'none (each baseline is its own family here)'}",
    ]
    peers = [g for g in exp.configs if g.peer]
    if peers:
        items.append("reference arms, not trained by mcrl (peer.json): "
                     + ", ".join(f"`{g.key}` ({g.peer})" for g in peers))
    if exp.extra_sources:
        items.append("runs added from: " + ", ".join(code(str(p)) for p in exp.extra_sources))
    out: list[Block] = [Heading(2, "Provenance and method"), Bullets(items)]
    resumed = _resumes(exp.runs)
    main = resumed.get(exp.dir.resolve(), [])
    if exp.provenance or main:
        out += [Paragraph("**Provenance** (from provenance.json):"), Bullets(_provenance(exp.provenance) + main)]
    for path in [p for p in exp.extra_sources if p.resolve() != exp.dir.resolve()]:
        prov, more = exp.extra_provenance.get(path, {}), resumed.get(path.resolve(), [])
        if prov or more:
            out += [Paragraph(f"**Provenance of {code(path.name)}** (from {code(str(path / 'provenance.json'))}):"),
                    Bullets(_provenance(prov) + more)]
    return out


def _resumes(runs: Sequence[Run]) -> dict[Path, list[str]]:
    """Per directory the runs were read from: one line counting every resume its runs record (a reference run's
    peer.json lists the step of each in ``resumed_at``), e.g. 'resumed (...): 2 of 12 runs, 4 resumes: s0 once,
    from step 110,000; s3 3 times, from steps 20,000, 20,000 and 60,000'. Directories without one are left out."""
    by_source: dict[Path, list[Run]] = {}
    for r in runs:
        if r.source is not None and r.status != "missing":
            by_source.setdefault(r.source.resolve(), []).append(r)
    out = {}
    for source, rs in by_source.items():
        at = {id(r): [int(s) for s in (r.peer or {}).get("resumed_at") or []] for r in rs}
        done = sorted((r for r in rs if at[id(r)]), key=lambda r: (r.seed is None, r.seed or 0, r.dir.name))
        if done:
            out[source] = [f"resumed (each run's peer.json, resumed_at): {len(done)} of {len(rs)} runs, "
                           f"{sum(len(at[id(r)]) for r in done)} resumes: "
                           + "; ".join(_resumed(r, at[id(r)]) for r in done)]
    return out


def _resumed(r: Run, at: list[int]) -> str:
    """'s3 3 times, from steps 20,000, 20,000 and 60,000'."""
    times = "once" if len(at) == 1 else "twice" if len(at) == 2 else f"{len(at)} times"
    where = ", ".join(steps(s) for s in at[:-1]) + (" and " if len(at) > 1 else "") + steps(at[-1])
    return f"{r.dir.name} {times}, from step{'s' if len(at) > 1 else ''} {where}"


def _provenance(prov: dict[str, object]) -> list[str]:
    """provenance.json's items, the known keys first, then each `mcrl sweep` call (`mcrl.sweep.provenance`);
    "machines" (run -> machine) is what "machine" summarises."""
    known = {"commit": "code commit", "machine": "machine", "command": "command", "rerun_one_seed": "re-run one seed"}
    order = [k for k in known if k in prov] + sorted(k for k in prov if k not in known and k not in ("machines",
                                                                                                   "sweeps"))
    calls = prov.get("sweeps")
    calls = calls if isinstance(calls, list) else []
    return ([f"{known.get(k, k)}: {code(str(prov[k]))}" for k in order]
            + [_sweep_call(i + 1, c) for i, c in enumerate(calls)])


def _sweep_call(i: int, c: object) -> str:
    """'sweep call 1: `mcrl sweep ...`, started 2026-12-03T10:00:00+00:00, ended ...; mcrl 0.2.0, commit
    `5c418ac...`; machine `AMD EPYC ..., 2 cores` (host `box`)'."""
    if not isinstance(c, dict):
        return f"sweep call {i}: {code(str(c))}"
    ended = f"ended {c['ended']}" if c.get("ended") else "no end recorded (killed, or still running)"
    commit = (f", commit {code(c['commit'])}" + (" with uncommitted changes" if c.get("dirty") else "")
              if c.get("commit") else ", not a git checkout")
    host = f" (host {code(c['host'])})" if c.get("host") else ""
    return (f"sweep call {i}: {code(c.get('command', '?'))}, started {c.get('started', '?')}, {ended}; "
            f"mcrl {c.get('mcrl', '?')}{commit}; machine {code(c.get('machine', '?'))}{host}")
