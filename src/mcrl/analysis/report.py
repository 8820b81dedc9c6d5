"""``mcrl report``: one self-contained report of an experiment (a sweep of runs over seeds).

Loads the experiment (:mod:`mcrl.analysis.experiment`) and the claims registry above it
(:mod:`mcrl.analysis.registry`), builds its sections and writes them as Markdown with PNG figures beside it, or as
one HTML file with the PNGs embedded (:mod:`mcrl.analysis.markdown`). The answer leads: the verdicts, then the
thesis' comparison, then the numbers and curves behind them, and how it was made last. Works on a partial sweep:
statistics of final values use finished runs only, learning curves use every run that has data, and a section
lists the runs that are missing or unfinished.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

from mcrl.analysis.comparison import thesis_section
from mcrl.analysis.experiment import Experiment, load_experiment
from mcrl.analysis.families import report_claims
from mcrl.analysis.intrinsic import intrinsic_section
from mcrl.analysis.markdown import Block, to_html, to_markdown
from mcrl.analysis.registry import Registry, find_registry, load_registry, repo_root
from mcrl.analysis.provenance import provenance
from mcrl.analysis.sections import results, summary
from mcrl.analysis.verdicts import verdict_section
from mcrl.errors import MCRLError

__all__ = ["load_experiment", "write_report"]  # load_experiment: re-exported, `mcrl sweep`'s tests read with it


def build_report(exp: Experiment, registry: Registry | None = None) -> list[Block]:
    """Every section of the report, in order: the answer first, provenance last."""
    root = repo_root(registry.path) if registry else None
    claims = report_claims(exp, registry, root)
    return (summary(exp) + verdict_section(claims, exp) + thesis_section(exp, claims) + intrinsic_section(exp, claims)
            + results(exp, claims) + provenance(exp, registry.shown(root) if registry else None))


def write_report(experiment_dir: str | Path, out_dir: str | Path | None = None,
                 fmt: Literal["md", "html"] = "md", extra_runs: Sequence[str | Path] = (),
                 claims: str | Path | bool | None = None) -> Path:
    """Write the report of an experiment directory; returns the report file's path.

    ``fmt="md"``: ``OUT/report.md`` with its PNG figures beside it; ``fmt="html"``: one
    self-contained ``OUT/report.html`` (figures embedded). ``out_dir`` defaults to ``EXP/report``.
    ``extra_runs``: more runs to include (see :func:`load_experiment`), e.g. reference arms.
    ``claims``: the claims registry (a claims.yaml); None finds one above the experiment directory
    (:func:`mcrl.analysis.registry.find_registry`), False uses none.
    Raises MCRLError when the directory does not exist, has no sweep.json, lists no runs, or no
    run has evaluated yet, or when the registry cannot be read.
    """
    if fmt not in ("md", "html"):
        raise MCRLError(f"unknown report format {fmt!r}: use --format md or --format html")
    from mcrl.decide.report import is_sequential, sequential_report  # a sequential plan's directory

    if is_sequential(experiment_dir):
        blocks = sequential_report(experiment_dir, extra_runs)
        return _write(blocks, Path(out_dir) if out_dir is not None else Path(experiment_dir) / "report", fmt,
                      Path(experiment_dir).name)
    exp = load_experiment(experiment_dir, extra_runs)
    path = find_registry(exp.dir) if claims is None or claims is True else None if claims is False else Path(claims)
    blocks = build_report(exp, load_registry(path) if path else None)  # before creating OUT: a failure leaves nothing
    return _write(blocks, Path(out_dir) if out_dir is not None else exp.dir / "report", fmt, exp.dir.name)


def _write(blocks: list[Block], out: Path, fmt: str, name: str) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    if fmt == "md":
        path = out / "report.md"
        path.write_text(to_markdown(blocks, out))
    else:
        path = out / "report.html"
        path.write_text(to_html(blocks, f"mcrl report: {name}"))
    return path
