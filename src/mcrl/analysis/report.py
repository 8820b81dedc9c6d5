"""``mcrl report``: one self-contained report of an experiment (a sweep of runs over seeds).

Loads the experiment (:mod:`mcrl.analysis.experiment`), builds its sections (:mod:`mcrl.analysis.sections`)
and writes them as Markdown with PNG figures beside it, or as one HTML file with the PNGs embedded
(:mod:`mcrl.analysis.markdown`). Works on a partial sweep: statistics of final values use finished runs only,
learning curves use every run that has data, and a section lists the runs that are missing or unfinished.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

from mcrl.analysis.experiment import load_experiment
from mcrl.analysis.markdown import to_html, to_markdown
from mcrl.analysis.sections import build_report
from mcrl.errors import MCRLError

__all__ = ["load_experiment", "write_report"]  # load_experiment: re-exported, `mcrl sweep`'s tests read with it


def write_report(experiment_dir: str | Path, out_dir: str | Path | None = None,
                 fmt: Literal["md", "html"] = "md", extra_runs: Sequence[str | Path] = ()) -> Path:
    """Write the report of an experiment directory; returns the report file's path.

    ``fmt="md"``: ``OUT/report.md`` with its PNG figures beside it; ``fmt="html"``: one
    self-contained ``OUT/report.html`` (figures embedded). ``out_dir`` defaults to ``EXP/report``.
    ``extra_runs``: more runs to include (see :func:`load_experiment`), e.g. reference arms.
    Raises MCRLError when the directory does not exist, has no sweep.json, lists no runs, or no
    run has evaluated yet.
    """
    if fmt not in ("md", "html"):
        raise MCRLError(f"unknown report format {fmt!r}: use --format md or --format html")
    exp = load_experiment(experiment_dir, extra_runs)
    blocks = build_report(exp)  # before creating OUT: a failing section leaves nothing behind
    out = Path(out_dir) if out_dir is not None else exp.dir / "report"
    out.mkdir(parents=True, exist_ok=True)
    if fmt == "md":
        path = out / "report.md"
        path.write_text(to_markdown(blocks, out))
    else:
        path = out / "report.html"
        path.write_text(to_html(blocks, f"mcrl report: {exp.dir.name}"))
    return path
