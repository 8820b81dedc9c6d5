"""Hand-written answers quote the committed reports' numbers: when a report is regenerated (a family grows, a level
changes), a study's answer that still quotes the old values fails here, not in an audit."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
INTRINSIC_REPORT = ROOT / "docs" / "intrinsic" / "fetchpush" / "report" / "report.md"
INTRINSIC_STUDY = ROOT / "docs" / "studies" / "intrinsic-runs.md"
ARMS = {"RND": "SAC+RND 0.2", "Disagreement": "SAC+Disagreement 0.2", "ICM": "SAC+ICM 0.2"}


def _cells(md: str, starts: str) -> list[str]:
    line = next(ln for ln in md.splitlines() if ln.startswith(f"| {starts}"))
    return [c.strip() for c in line.strip("|").split("|")]


def _adjusted(md: str, claim: str) -> str:
    """The Holm-adjusted p of the verdict table's claim, as the answer quotes it (two significant digits)."""
    p = float(re.fullmatch(r"\S+ \((\S+)\)", _cells(md, claim)[6]).group(1))  # type: ignore[union-attr]
    return f"{p:#.2g}"


def test_the_intrinsic_studys_answer_quotes_the_report() -> None:
    md, study = INTRINSIC_REPORT.read_text(), INTRINSIC_STUDY.read_text()
    answer = study[study.index("**Answer"):study.index("## The runs")]
    sac = {a: _adjusted(md, f"{x} > mcrl SAC") for a, x in ARMS.items()}
    mc = {a: _adjusted(md, f"{x} differs from mcrl SAC-MC 0.2") for a, x in ARMS.items()}
    assert (f"Against SAC the adjusted p is {sac['RND']} (RND), {sac['Disagreement']} (Disagreement) and "
            f"{sac['ICM']} (ICM)") in " ".join(answer.split())
    assert f"Against SAC-MC it is {mc['RND']}, {mc['Disagreement']} and {mc['ICM']}" in " ".join(answer.split())
    section = md[md.index("## Other intrinsic rewards against SAC and SAC-MC"):md.index("## Final performance")]
    powers = [float(ln.strip("|").split("|")[-1].split()[0]) for ln in section.splitlines() if ln.startswith("| `")]
    assert len(powers) == 6
    assert f"power {min(powers):.2f} to {max(powers):.2f}" in " ".join(answer.split())
