"""The claims registry (issue 49): one declared family per baseline arm, read by every report, so a claim gets the
same family-adjusted p-value wherever it is printed, and its family's size is what the registry declares."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from mcrl.analysis.claims import claim_power, claim_test, decide
from mcrl.analysis.experiment import load_experiment
from mcrl.analysis.families import report_claims
from mcrl.analysis.markdown import to_markdown
from mcrl.analysis.registry import find_registry, load_registry
from mcrl.analysis.report import write_report
from mcrl.analysis.verdicts import verdict_section
from mcrl.errors import MCRLError

sys.path.insert(0, str(Path(__file__).parent))
from test_report import _row, _section, _sweep  # noqa: E402  (the fake run directories of the report tests)

SAC = [0.05, 0.1, 0.2, 0.3, 0.35, 0.5]
SAC_MC = [0.4, 0.5, 0.6, 0.7, 0.75, 0.8]
VARIANT = [0.3, 0.45, 0.55, 0.6, 0.8, 0.9]
RND = [0.1, 0.2, 0.25, 0.4, 0.45, 0.55]
REGISTRY = """
arms:
  SAC: {dir: main, select: {mc_alpha: 0}}
  SAC-MC 0.2: {dir: main, select: {mc_alpha: 0.2}}
  variant: {dir: variant}
  RND: {dir: arms, select: {intrinsic: rnd}}
  SAC-MC 0.4: {dir: alpha, select: {mc_alpha: 0.4}}
families:
  - baseline: SAC
    claims:
      - {x: SAC-MC 0.2, is: better, by: 0.23}
      - {x: variant, is: better, by: 0.23}
      - {x: RND, is: better, by: 0.23}
      - {x: SAC-MC 0.4, is: same, margin: 0.115}
"""


@pytest.fixture
def repo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A repository whose docs/ holds the registry and three experiments sharing the SAC arm."""
    monkeypatch.delenv("MCRL_CLAIMS", raising=False)
    docs = tmp_path / "repo" / "docs"
    (tmp_path / "repo" / ".git").mkdir(parents=True)
    _sweep(docs / "main", {"sac": (0.0, {}, SAC), "sacmc": (0.2, {}, SAC_MC)})
    _sweep(docs / "variant", {"variant": (0.2, {"mc_reduction": "batch", "mc_state": "full"}, VARIANT)})
    _sweep(docs / "arms", {"rnd": (0.2, {"intrinsic": "rnd"}, RND)})
    (docs / "claims.yaml").write_text(REGISTRY)
    return docs


def _claim(md: str, x: str) -> list[str]:
    """The verdict table's row of the claim whose X is the registry's arm ``x``."""
    return _row(_section(md, "Verdicts"), f"{x} ")


def _verdicts(docs: Path, exp: str, *extra: str) -> str:
    claims = report_claims(load_experiment(docs / exp, [docs / e for e in extra]), load_registry(docs / "claims.yaml"),
                           docs.parent)
    return to_markdown(verdict_section(claims), docs)


def test_two_reports_print_the_same_family_adjusted_p(repo: Path) -> None:
    a = _verdicts(repo, "main", "variant")  # the reproduction's layout: SAC, SAC-MC and the variant
    b = _verdicts(repo, "arms", "main")  # the intrinsic report's: RND beside SAC and SAC-MC
    for x in ("SAC-MC 0.2", "RND"):  # RND's claim is printed in the report that does not hold its runs, too
        assert _claim(a, x)[2:] == _claim(b, x)[2:]  # the same family, seeds, intervals, p, power and verdict
    # the adjusted p is Holm over the family's claims with seeds: three of the four declared
    tests = [claim_test(x, SAC, 0.23) for x in (SAC_MC, VARIANT, RND)]
    adjusted = decide(tests)[0].p_adj
    assert _claim(a, "SAC-MC 0.2")[6] == f"{tests[0].p:.4f} ({adjusted:.4f})" and adjusted > tests[0].p
    assert "- 'against SAC': 4 claims, Holm over the 3 with enough seeds" in a and "against SAC': 4 claims" in b


def _sacmc(docs: Path, exp: str, *extra: str, registry: bool = True):
    """The decided claim 'SAC-MC 0.2 better than SAC' of a report (no effect sizes: no bootstrap)."""
    claims = report_claims(load_experiment(docs / exp, [docs / e for e in extra]),
                           load_registry(docs / "claims.yaml") if registry else None, docs.parent)
    return next(r for r in claims.results if r.kind == "better" and r.x.tolist() == SAC_MC)


def test_the_family_grows_where_the_registry_says_and_nowhere_else(repo: Path) -> None:
    (repo / "alpha").mkdir()
    (repo / "alpha" / "run.sh").write_text("mcrl sweep ...\n")  # declared and set up, no run yet: 0 seeds
    before = _sacmc(repo, "main")
    _sweep(repo / "alpha", {"a0.4": (0.4, {}, [s + 0.02 for s in SAC])})  # the declared alpha arm gets its runs
    after, elsewhere = _sacmc(repo, "main"), _sacmc(repo, "arms", "main")
    assert (before.family.size, before.family.with_seeds, after.family.with_seeds) == (4, 3, 4)
    assert after.verdict.p_adj > before.verdict.p_adj  # Holm over 4 claims now, in every report
    assert elsewhere.verdict.p_adj == after.verdict.p_adj and elsewhere.family == after.family


def test_a_report_finds_the_registry_above_its_experiment(repo: Path, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    assert find_registry(repo / "main") == repo / "claims.yaml"
    assert find_registry(tmp_path / "repo") is None  # up to the repository's root, not beyond
    monkeypatch.setenv("MCRL_CLAIMS", "none")
    assert find_registry(repo / "main") is None
    monkeypatch.delenv("MCRL_CLAIMS")
    md = write_report(repo / "arms", tmp_path / "rep", extra_runs=[repo / "main"]).read_text()
    assert "claims registry: `docs/claims.yaml`" in md and "declared in docs/claims.yaml" in md
    assert md.index("## Verdicts") < md.index("## Comparison with the thesis") < md.index("## Learning curves") \
        < md.index("## Final performance per seed") < md.index("## Provenance and method")
    row = _row(_section(md, "Other intrinsic rewards against SAC and SAC-MC"), "`SAC+RND 0.2` | `SAC`")
    assert row[4] == _claim(md, "RND")[6]  # the section prints its family's p
    p = claim_test(SAC_MC, SAC, 0.23).p
    assert _claim(md, "SAC-MC 0.2")[6] == f"{p:.4f} ({3 * p:.4f})"  # Holm over the declared family's 3
    # without the registry the report forms the family from its own claims (SAC-MC's and RND's): another p
    alone = _sacmc(repo, "arms", "main", registry=False)
    assert alone.verdict.p_adj == pytest.approx(2 * p) and alone.family.declared_in is None


def test_pooled_baselines_wait_for_their_equivalence(repo: Path) -> None:
    (repo / "claims.yaml").write_text(REGISTRY + """
  - baseline: variant
    claims:
      - {x: SAC, is: same, margin: 0.115}
  - baseline: {name: pooled, pool: [SAC, variant]}
    requires: SAC same as variant
    claims:
      - {x: SAC-MC 0.2, is: better, by: 0.23}
""")
    claims = report_claims(load_experiment(repo / "main"), load_registry(repo / "claims.yaml"), repo.parent)
    pooled = next(r for r in claims.results if r.y_name == "pooled")
    assert pooled.y.size == 12 and pooled.verdict.p_adj is None and pooled.family.blocked
    assert "blocked by its requirement 'SAC same as variant' (family 'against variant')" in pooled.note


@pytest.mark.parametrize("text, says", [
    ("families: [{baseline: nope, claims: []}]", "not defined under 'arms'"),
    ("arms: {A: {dir: a}}\nfamilies: [{baseline: A, claims: [{x: A, is: bigger}]}]", "'is' must be one of"),
    ("arms: {A: {dir: a}}\nfamilies: [{baseline: A, claims: [{x: A, is: same}]}]", "positive 'margin'"),
    ("arms: {A: {dir: a}}\nfamilies: [{baseline: A, claims: []}, {baseline: A, claims: []}]", "one family per baseline"),
    ("arms: {A: {dir: a}}\nfamilies: [{baseline: A, requires: x, claims: []}]", "requires claim 'x'"),
    ("arms: {A: {dir: a, pool: [A]}}\nfamilies: [{baseline: A, claims: []}]", "either 'dir'"),
    ("claims: []", "needs a 'families' list"),
])
def test_a_bad_registry_says_what_to_fix(tmp_path: Path, text: str, says: str) -> None:
    path = tmp_path / "claims.yaml"
    path.write_text(text)
    with pytest.raises(MCRLError, match=says) as e:
        load_registry(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


POOLED = REGISTRY + """
  - baseline: variant
    claims:
      - {x: SAC, is: same, margin: 0.115}
  - baseline: {name: pooled, pool: [SAC, variant]}
    requires: SAC same as variant
    claims:
      - {x: SAC-MC 0.2, is: better, by: 0.23}
      - {x: RND, is: better, by: 0.23}
"""


def test_a_blocked_familys_power_is_at_the_level_its_claims_will_be_tested_at(repo: Path) -> None:
    """Two claims against the pooled baseline: once unblocked, Holm tests the first at 0.05 / 2, so that is the
    level of their power (not 0.05, as if the family had one claim), and the report says so."""
    (repo / "claims.yaml").write_text(POOLED)
    claims = report_claims(load_experiment(repo / "main", [repo / "arms"]), load_registry(repo / "claims.yaml"),
                           repo.parent)
    pooled = [r for r in claims.results if r.y_name == "pooled"]
    assert len(pooled) == 2 and all(r.verdict.p_adj is None and r.family.blocked for r in pooled)
    for r in pooled:
        assert r.level == pytest.approx(0.025)
        assert r.power == pytest.approx(claim_power(r.kind, r.by, r.x, r.y, 0.025))
        assert r.power != pytest.approx(claim_power(r.kind, r.by, r.x, r.y, 0.05))
    md = to_markdown(verdict_section(claims), repo)
    assert [_verdict_row(md, x, "> pooled")[8] for x in ("SAC-MC 0.2", "RND")] == [
        f"{r.power:.2f} at 0.025" for r in pooled]
    # a tested family's power is at its own first level: 0.05 / 3, its claims with seeds
    sac = next(r for r in claims.results if r.y_name == "SAC" and r.x_name == "SAC-MC 0.2")
    assert sac.level == pytest.approx(0.05 / 3) and _verdict_row(md, "SAC-MC 0.2", "> SAC")[8] == (
        f"{sac.power:.2f} at 0.0167")


def _verdict_row(md: str, x: str, has: str) -> list[str]:
    """The verdict table's row of the claim whose X is the registry's arm ``x`` and whose statement has ``has``."""
    line = next(ln for ln in _section(md, "Verdicts").splitlines() if ln.startswith(f"| {x} ") and has in ln)
    return [c.strip() for c in line.strip("|").split("|")]


def test_a_blocked_family_says_it_is_blocked_and_by_what(repo: Path) -> None:
    """Not 'Holm over the 0 with enough seeds': the family is not tested, because the claim it requires (named,
    with its family and verdict) is not reproduced; once it is, Holm runs over its claims with seeds."""
    (repo / "claims.yaml").write_text(POOLED)
    claims = report_claims(load_experiment(repo / "main", [repo / "arms"]), load_registry(repo / "claims.yaml"),
                           repo.parent)
    md = to_markdown(verdict_section(claims), repo)
    why = ("blocked by its requirement 'SAC same as variant' (family 'against variant'), which is not decidable "
           "with this many seeds")
    assert (f"- 'against pooled': 2 claims, not tested: {why}; once that claim is reproduced, Holm over the 2 with "
            "enough seeds (first level 0.025)") in md
    assert "Holm over the 0" not in md
    assert _verdict_row(md, "SAC-MC 0.2", "> pooled")[9] == (
        f"**not decidable with this many seeds**: its family is not tested: {why}")
    assert "- 'against SAC': 4 claims, Holm over the 3 with enough seeds" in md  # a tested family as before
