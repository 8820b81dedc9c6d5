"""The report's first section: every claim it decides, in one table, with its family, interval, seeds and power;
and the sentence that states one claim's tests, which the thesis sections share."""

from __future__ import annotations

from mcrl.analysis.cells import interval, num, other_intrinsic, pvalue, reference_sac, sac_and_mc
from mcrl.analysis.claims import LEVEL, NOT_DECIDABLE, outcome, statement
from mcrl.analysis.experiment import Experiment
from mcrl.analysis.families import ClaimResult, Family, ReportClaims
from mcrl.analysis.markdown import Block, Bullets, Heading, Paragraph, Table
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT


def _p(p: float | None, adj: float | None) -> str:
    if p is None:
        return "-"
    return f"{pvalue(p)} ({pvalue(adj)})" if adj is not None else f"{pvalue(p)} (unadjusted)"


def _name(r: ClaimResult, side: str) -> str:
    """An arm as the table names it: the registry's name, with the report's label where they differ."""
    name, group = (r.x_name, r.x_group) if side == "x" else (r.y_name, r.y_group)
    return name if group is None or name in (group.key, f"`{group.key}`") else f"{name} (`{group.key}`)"


def level(a: float) -> str:
    """A test level as the report prints it: 0.05, 0.025, 0.0167, 0.00556."""
    return f"{a:.3g}"


def power_cell(r: ClaimResult) -> str:
    """'0.58 at 0.025': the claim's power and the level it is computed at (its family's first Holm level)."""
    return "n/a" if r.power != r.power else f"{num(r.power, 2)} at {level(r.level)}"


def verdict_cell(r: ClaimResult) -> str:
    """'**reproduced** (better)', '**not decidable**: too few seeds', ..."""
    if r.note:
        return f"**{NOT_DECIDABLE}**: {r.note}"
    if r.verdict.p_adj is None:
        return f"**{NOT_DECIDABLE}**: fewer than {MIN_SEEDS_FOR_VERDICT} seeds in an arm"
    said = outcome(r.kind, r.verdict.verdict, r.by, r.test.x_above)
    return f"**{r.verdict.verdict}**" + ("" if r.verdict.verdict == NOT_DECIDABLE else f" ({said})")


def _family_note(f: Family) -> str:
    """'against X': its size and the m of its Holm correction, or, where it is blocked, by what."""
    head = f"'{f.name}'{'' if f.declared_in else ' (this report)'}: {f.size} claims"
    if f.blocked:
        return (f"{head}, not tested: {f.blocked}; once that claim is reproduced, Holm over the {f.with_seeds} with "
                f"enough seeds (first level {level(f.level)})")
    return f"{head}, Holm over the {f.with_seeds} with enough seeds"


def no_claim(exp: Experiment | None) -> str:
    """Why a report decides no claim, from the arms it holds (the old sentence blamed a missing SAC arm even where
    the tables showed one)."""
    if exp is None:
        return "No claim to decide: the report's arms imply none."
    sac, mc = sac_and_mc(exp)
    sacs, others = sac + reference_sac(exp), other_intrinsic(exp)
    if not sacs:
        return ("No claim to decide: the report has no finished SAC arm (intrinsic_alpha = 0), the baseline of every "
                "claim; add one with `--with DIR`.")
    if not mc and not others:
        return "No claim to decide: every finished arm is SAC (intrinsic_alpha = 0), so there is nothing to compare."
    return ("No claim to decide: the thesis' claims on this task are about SAC-MC alpha 0.2 (against any SAC) and "
            "its alpha curve (against mcrl's SAC), and no arm here is one of them.")


def verdict_section(claims: ReportClaims, exp: Experiment | None = None) -> list[Block]:
    """The table of every claim, family by family; `exp` says why there is none."""
    out: list[Block] = [Heading(2, "Verdicts")]
    if not claims.results:
        return out + [Paragraph(no_claim(exp))]
    reg = claims.registry
    where = (f"declared in {reg.shown(claims.root)} (the claims registry: one family per baseline arm, shared by "
             "every report that prints one of its claims)" if reg else "not declared in a claims registry (none was "
             "found above the experiment directory): each baseline's family is this report's claims against it")
    rows = []
    for r in claims.results:
        few = r.verdict.p_adj is None and not r.note
        (p, plo, phi), (d, dlo, dhi) = r.effects if min(r.x.size, r.y.size) >= MIN_SEEDS_FOR_VERDICT else (
            (float("nan"),) * 3, (float("nan"),) * 3)
        rows.append([statement(r.kind, _name(r, "x"), _name(r, "y"), r.by), r.source or "-", r.family.name,
                     f"{r.x.size} / {r.y.size}", "-" if few else f"{d:+.3f} [{dlo:+.3f}, {dhi:+.3f}]",
                     "-" if few else f"{p:.3f} {interval((plo, phi), 3)}",
                     "-" if few else _p(r.test.p, r.verdict.p_adj),
                     "-" if few else _p(r.test.p_refute if r.verdict.p_refute_adj is not None else None,
                                        r.verdict.p_refute_adj),
                     power_cell(r), verdict_cell(r)])
    notes = [_family_note(f) for f in {r.family.name: r.family for r in claims.results}.values()]
    return out + [
        Paragraph(f"Each claim compares the final success rate of X with baseline Y by exact rank-sum tests "
                  f"(mcrl.analysis.claims) at level {LEVEL}: 'reproduced' when the claim's own test is significant "
                  "after Holm's correction over its family (the claims against the same baseline arm), 'not "
                  "reproduced' when its opposite is (an improvement or deficit as large as claimed excluded, or a "
                  "difference beyond the margin shown), else 'not decidable'. The claims are "
                  f"{where}. Mean difference X - Y and P(X > Y) with 95% bootstrap intervals; power: the chance "
                  "these seeds reproduce the claim if it holds as stated, at the level given: its family's first "
                  "Holm level, 0.05 / m over the family's m claims with enough seeds (of a family not tested yet: "
                  "the level its claims will first be tested at). A claim whose own p reaches it is reproduced "
                  "whatever the other claims' p-values."),
        Table(["claim", "from", "family", "seeds X / Y", "mean difference [95% CI]", "P(X > Y) [95% CI]",
               "p (adjusted)", "p of its opposite (adjusted)", "power", "verdict"], rows),
        Paragraph("Families:"), Bullets(notes),
    ]


def tests_sentence(r: ClaimResult) -> str:
    """The claim's tests and p-values, e.g. 'one-sided exact rank-sum test of X > Y: p = 0.0147 (Holm-adjusted
    over ...: 0.0736); of X falling short of Y +0.23: p = 0.6172 (adjusted 1.0000)'."""
    t, v, fam = r.test, r.verdict, r.family.phrase()
    adj = "unadjusted" if v.p_adj is None else pvalue(v.p_adj)
    radj = "unadjusted" if v.p_refute_adj is None else pvalue(v.p_refute_adj)
    if r.kind == "same":
        m = f"{r.by:.3g}"
        return (f"two one-sided exact rank-sum tests, X + {m} > Y: p = {pvalue(t.parts[0])} and X - {m} < Y: "
                f"p = {pvalue(t.parts[1])}, so equivalence p = {pvalue(t.p)} ({fam}: {adj}); of X beyond Y +/- {m}: "
                f"p = {pvalue(t.p_refute)} (adjusted {radj})")
    if r.kind == "worse":
        by = "" if r.by is None else (f"; of X + {r.by:.2f} above Y (a deficit of {r.by:.2f} excluded): "
                                      f"p = {pvalue(t.p_refute)} (adjusted {radj})")
        return f"one-sided exact rank-sum test of X < Y: p = {pvalue(t.p)} ({fam}: {adj}){by}"
    if r.kind == "differs":
        return f"two-sided exact rank-sum test: p = {pvalue(t.p)} ({fam}: {adj})"
    by = "" if r.by is None else (f"; of X falling short of Y {r.by:+.2f}: p = {pvalue(t.p_refute)} "
                                  f"(adjusted {radj})")
    return f"one-sided exact rank-sum test of X > Y: p = {pvalue(t.p)} ({fam}: {adj}){by}"


def power_sentence(r: ClaimResult) -> str:
    at = f"level {level(r.level)}, normal scores with the observed SDs"
    if r.kind == "same":
        return (f"Power of these seeds to show equivalence within {r.by:.3g} when there is no difference: "
                f"{num(r.power, 2)} (two one-sided rank-sum tests at {at}).")
    size = "n/a" if r.by is None else f"{r.by:+.2f}" if r.kind == "better" else f"{-r.by:+.2f}"
    what = f"the thesis' {size}" if r.source.startswith("thesis") and r.kind == "better" else f"a difference of {size}"
    return f"Power of these seeds to detect {what}: {num(r.power, 2)} (rank-sum test at {at})."
