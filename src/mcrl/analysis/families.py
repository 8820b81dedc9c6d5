"""The claims a report decides and the families their Holm correction runs over.

A report's arms imply claims (:func:`candidates`): SAC-MC alpha 0.2 and the thesis' code's variant better than each
SAC arm, each arm with another intrinsic reward better than each SAC arm and different from each SAC-MC arm, and the
thesis' alpha curve against mcrl's SAC (0.4 and 0.6 about the same, 0.8 and 1.0 worse). On a task the thesis has
no numbers for (FetchReach), every SAC-MC arm is claimed better than each SAC arm, without a size, as an exploration
bonus is. Where the claims registry
(:mod:`mcrl.analysis.registry`) declares a family for the baseline, the claim is decided inside that family, from the
registry's runs, so every report prints the same adjusted p-value for it; a claim the registry does not declare
against such a baseline gets no verdict (exploratory). A baseline the registry does not know forms its family from
this report's claims against it, as before the registry existed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from mcrl.analysis.cells import CONF, SEED, is_code_variant, is_scheduled, other_intrinsic, reference_sac, sac_and_mc
from mcrl.analysis.claims import LEVEL, NOT_DECIDABLE, ClaimTest, Verdict, claim_power, claim_test, decide
from mcrl.analysis.experiment import ConfigGroup, Experiment
from mcrl.analysis.registry import ArmRuns, ArmSpec, FamilySpec, Registry
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT, mean_difference_ci, probability_of_improvement
from mcrl.analysis.thesis import THESIS_RESULTS, equivalence_margin, env_ids, thesis_experiment, thesis_gain

CODE_VARIANT = "the thesis' code's variant of SAC-MC alpha=0.2 (one batch-mean KL, the whole observation)"


@dataclass(frozen=True)
class Family:
    """The Holm family a claim was decided in."""

    name: str  # "against mcrl SAC"
    declared_in: str | None  # the registry file as shown; None: this report's own claims against the baseline
    size: int  # claims in the family
    with_seeds: int  # of them with enough seeds: the m of Holm's correction (a blocked family's once it is tested)
    blocked: str | None = None  # why the family is not tested: "blocked by its requirement '...' (family '...'), ..."

    @property
    def level(self) -> float:
        """Holm's first level, LEVEL / m: a claim whose own p-value reaches it is reproduced whatever the other
        claims' p-values, so the power computed at it is the least chance the claim has (of a blocked family: once
        the family is tested)."""
        return LEVEL / max(self.with_seeds, 1)

    def phrase(self) -> str:
        """How a claim's adjusted p-value was adjusted, in words."""
        if self.declared_in is None:
            return ("the only claim against this baseline, so unadjusted" if self.with_seeds <= 1 else
                    f"Holm-adjusted over the {self.with_seeds} claims against this baseline in this report")
        seeds = "" if self.with_seeds == self.size else f", {self.with_seeds} with enough seeds"
        return f"Holm-adjusted over the family '{self.name}' of {self.declared_in} ({self.size} claims{seeds})"


@dataclass
class ClaimResult:
    """One claim, decided: X is ``kind`` than Y (by ``by``), in ``family``."""

    id: str
    kind: str
    by: float | None
    x_name: str
    y_name: str
    x: np.ndarray  # final success per seed
    y: np.ndarray
    test: ClaimTest
    verdict: Verdict
    family: Family
    power: float  # at Holm's first level of its family, :attr:`level`
    source: str = ""
    x_group: ConfigGroup | None = None  # the report's arms, where they are in it
    y_group: ConfigGroup | None = None
    what: str = ""  # the thesis' name for X, for the thesis section
    note: str = ""  # why there is no verdict, beyond the seeds
    exploratory: bool = False  # a claim the registry does not declare against its baseline: no verdict

    @cached_property
    def effects(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """P(X > Y) and the mean difference X - Y, each with its 95% bootstrap interval."""
        return (probability_of_improvement(self.x, self.y, conf=CONF, seed=SEED),
                mean_difference_ci(self.x, self.y, conf=CONF, seed=SEED))

    @property
    def level(self) -> float:
        """The level its power is computed at: its family's first Holm level (:attr:`Family.level`)."""
        return self.family.level


@dataclass(frozen=True)
class Candidate:
    x: ConfigGroup
    y: ConfigGroup
    kind: str
    by: float | None
    what: str
    source: str


@dataclass
class ReportClaims:
    results: list[ClaimResult]
    registry: Registry | None = None
    root: Path | None = None  # where the registry's paths are shown from

    def find(self, x: ConfigGroup, y: ConfigGroup, kind: str) -> ClaimResult | None:
        return next((r for r in self.results if r.x_group is x and r.y_group is y and r.kind == kind), None)


def candidates(exp: Experiment) -> list[Candidate]:
    """The claims this report's arms imply (see the module docstring), each baseline's together."""
    thesis = thesis_experiment(exp.preset, env_ids(exp.runs))
    d, margin = thesis_gain(thesis), equivalence_margin(thesis)
    sac, mc = sac_and_mc(exp)
    others = other_intrinsic(exp)
    curve = (THESIS_RESULTS.get(thesis or "") or {}).get("alpha_curve", {})
    out: list[Candidate] = []
    for y in [*sac, *reference_sac(exp)]:
        if d is not None:
            out += [Candidate(x, y, "better", d, CODE_VARIANT if is_code_variant(x) else "SAC-MC alpha=0.2",
                              f"thesis, {THESIS_RESULTS[thesis or '']['tables']}")  # type: ignore[index]
                    for x in mc if math.isclose(x.intrinsic_alpha or 0.0, 0.2)]
        else:  # no thesis numbers to test: the thesis' direction alone, at every alpha (no curve to follow either)
            out += [Candidate(x, y, "better", None, f"`{x.key}`", "the thesis' claim, on a task without its numbers")
                    for x in mc]
        out += [Candidate(x, y, "better", d, f"`{x.key}`", "issue 67: a schedule's claim" if is_scheduled(x)
                          else "issue 29: an exploration bonus's claim") for x in others]
        if y.peer is None:  # the thesis' alpha curve, against the SAC the thesis ran: mcrl's
            for x in mc:
                a = next((a for a in curve if math.isclose(x.intrinsic_alpha or 0.0, a)), None)
                if a is not None and not is_code_variant(x):
                    kind = curve[a]["claim"]
                    out.append(Candidate(x, y, kind, margin if kind == "same" else d, f"SAC-MC alpha={a:g}",
                                         "thesis, section 4.1.3"))
    out += [Candidate(x, z, "differs", d, f"`{x.key}`", "issue 67" if is_scheduled(x) else "issue 29")
            for z in mc for x in others]
    return out


def _decide(kinds: list[str], bys: list[float | None], xs: list[np.ndarray], y: np.ndarray,
            blocked: bool = False) -> tuple[list[ClaimTest], list[Verdict], list[float], int]:
    """Tests, verdicts (Holm within the family) and power at Holm's first level of one family's claims, and how
    many of them have enough seeds: Holm's m. A blocked family gets no verdicts, and its power is at the level
    its claims will be tested at once it is unblocked (LEVEL / m, not LEVEL)."""
    tests = [claim_test(x, y, by, kind) for x, by, kind in zip(xs, bys, kinds)]  # type: ignore[arg-type]
    m = sum(min(t.n_x, t.n_y) >= MIN_SEEDS_FOR_VERDICT for t in tests)  # as decide() counts them
    verdicts = [Verdict(NOT_DECIDABLE, None, None, 0)] * len(tests) if blocked else decide(tests)
    power = [claim_power(k, by, x, y, LEVEL / max(m, 1))  # type: ignore[arg-type]
             for k, by, x in zip(kinds, bys, xs)]
    return tests, verdicts, power, m


class _Declared:
    """The registry's families, decided from the registry's own runs (the same in every report)."""

    def __init__(self, registry: Registry, root: Path | None) -> None:
        self.registry, self.runs = registry, ArmRuns()
        self.shown = registry.shown(root)
        self._done: dict[int, list[ClaimResult]] = {}

    def finals(self, arm: ArmSpec) -> np.ndarray:
        return np.array([r.final[0] for r in self.runs.runs(arm)], dtype=float)  # type: ignore[index]

    def family(self, f: FamilySpec) -> list[ClaimResult]:
        key = id(f)
        if key in self._done:
            return self._done[key]
        self._done[key] = []  # a family that requires itself, through others, stays untested
        blocked = None
        if f.requires is not None:
            fam, claim = self.registry.find(f.requires)  # type: ignore[misc]
            req = next(r for r in self.family(fam) if r.id == claim.id)
            if req.verdict.verdict != "reproduced":
                blocked = (f"blocked by its requirement '{f.requires}' (family '{fam.name}'), which is "
                           f"{req.verdict.verdict}")
        y, xs = self.finals(f.baseline), [self.finals(c.x) for c in f.claims]
        tests, verdicts, power, m = _decide([c.kind for c in f.claims], [c.by for c in f.claims], xs, y,
                                            blocked is not None)
        fam = Family(f.name, self.shown, len(f.claims), m, blocked)
        out = [ClaimResult(c.id, c.kind, c.by, c.x.name, f.baseline.name, x, y, t, v, fam, pw, c.source,
                           note=f"its family is not tested: {blocked}" if blocked else "")
               for c, x, t, v, pw in zip(f.claims, xs, tests, verdicts, power)]
        self._done[key] = out
        return out


def _dirs(g: ConfigGroup) -> frozenset[Path]:
    return frozenset(r.dir.resolve() for r in g.finished)


def report_claims(exp: Experiment, registry: Registry | None, root: Path | None = None) -> ReportClaims:
    """Every claim this report decides: the registry's families that share a run with it, then the families of
    baselines the registry does not know (this report's own)."""
    cands = candidates(exp)
    results: list[ClaimResult] = []
    declared_bases: set[int] = set()
    if registry is not None:
        dec = _Declared(registry, root)
        groups = {_dirs(g): g for g in exp.configs if g.finished}
        ours = frozenset().union(*groups) if groups else frozenset()
        for f in registry.families:
            arms = [f.baseline, *(c.x for c in f.claims)]
            if not any(dec.runs.dirs(a) & ours for a in arms):
                continue
            base_group = groups.get(dec.runs.dirs(f.baseline))
            if base_group is not None and f.claims:
                declared_bases.add(id(base_group))
            for c, r in zip(f.claims, dec.family(f)):
                r.y_group, r.x_group = base_group, groups.get(dec.runs.dirs(c.x))
                match = next((k for k in cands if k.x is r.x_group and k.y is r.y_group and k.kind == r.kind), None)
                r.what = match.what if match else f"`{r.x_group.key}`" if r.x_group else r.x_name
                results.append(r)
    own: dict[int, list[Candidate]] = {}
    for k in cands:
        if any(r.x_group is k.x and r.y_group is k.y and r.kind == k.kind for r in results):
            continue
        if id(k.y) in declared_bases:  # the registry has this baseline's family, but not this claim
            x, y = k.x.finals()[0], k.y.finals()[0]
            t = claim_test(x, y, k.by, k.kind)  # type: ignore[arg-type]
            fam = next(r.family for r in results if r.y_group is k.y)
            results.append(ClaimResult(f"{k.x.key} {k.kind} {k.y.key}", k.kind, k.by, f"`{k.x.key}`",
                                       f"`{k.y.key}`", x, y, t,
                                       Verdict(NOT_DECIDABLE, None, None, 0), fam, math.nan, k.source, k.x, k.y,
                                       k.what, f"not declared in {fam.declared_in}: exploratory, no verdict",
                                       exploratory=True))
        else:
            own.setdefault(id(k.y), []).append(k)
    for ks in own.values():
        y = ks[0].y.finals()[0]
        xs = [k.x.finals()[0] for k in ks]
        tests, verdicts, power, m = _decide([k.kind for k in ks], [k.by for k in ks], xs, y)
        fam = Family(f"against `{ks[0].y.key}`", None, len(ks), m)
        results += [ClaimResult(f"{k.x.key} {k.kind} {k.y.key}", k.kind, k.by, f"`{k.x.key}`", f"`{k.y.key}`", x,
                                y, t, v, fam, pw, k.source, k.x, k.y, k.what)
                    for k, x, t, v, pw in zip(ks, xs, tests, verdicts, power)]
    return ReportClaims(results, registry, root)


