"""A sequential plan: the YAML file a confirmatory experiment keeps beside its runs (``EXP/plan.yaml``).

Everything the decision depends on is fixed here before any data: the arms (one preset, overrides per arm), the
fresh seeds in the order they run, the batch (seeds an arm per look) and so the maximum, the claims (one primary,
any secondary) with each claim's share of the family's one-sided level, how a confirmed claim's level passes to the
others, the spending functions, the futility rule and its planning effect, and the commit the runs use. The file's
hash goes into every look (`mcrl.decide.runner`); a plan that changes after its first look is refused.

Example (docs/confirmatory/fetchpush/plan.yaml is a real one)::

    preset: fetchreach-sac
    set: {total_steps: 2000}            # every arm (optional)
    arms:                               # name: overrides of the preset
      sac: {intrinsic_alpha: 0.0}
      sacmc: {intrinsic_alpha: 0.2}
    seeds: 1000..1011                   # or a list; the maximum per arm is their number
    batch: 4                            # seeds an arm per look
    level: 0.05                         # family-wise, one-sided
    multiplicity: holm                  # or bonferroni
    claims:
      - name: mc-helps
        primary: true
        better: sacmc                   # the claim: this arm's finals tend to be larger ...
        than: sac                       # ... than this one's (one-sided rank-sum test)
        level: 0.05                     # this claim's share of the family's level
        spending: pocock                # or obrien-fleming, or power (with rho)
        futility: {beta: 0.15, spending: pocock, effect: 0.72}   # non-binding; effect = planning P(X > Y)
    commit: 0123abc...                  # optional: the code the runs must use
"""
from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mcrl.decide.boundaries import SPENDING
from mcrl.errors import MCRLError

PLAN_KEYS = ("name", "description", "commit", "preset", "set", "arms", "seeds", "batch", "metric", "test", "level",
             "multiplicity", "claims")
CLAIM_KEYS = ("name", "primary", "better", "than", "level", "spending", "rho", "futility", "note")
FUTILITY_KEYS = ("beta", "spending", "rho", "effect")
METRICS = ("final_success",)  # final_eval.json's success_rate: the thesis' and the reports' metric
TESTS = ("rank-sum",)  # one-sided, mid-ranks, tie-corrected variance (mcrl.decide.look.rank_sum_z)
MULTIPLICITY = ("holm", "bonferroni")


@dataclass(frozen=True)
class Futility:
    beta: float
    spending: str
    rho: float
    effect: float  # the planning P(X > Y) under which `beta` is spent

    @property
    def theta(self) -> float:
        """The planning drift: E[Z] = theta sqrt(I) with I = n_x n_y / (n_x + n_y + 1)."""
        return (self.effect - 0.5) * math.sqrt(12.0)


@dataclass(frozen=True)
class Claim:
    name: str
    better: str  # arm X
    than: str  # arm Y
    level: float  # its share of the family's one-sided level
    spending: str
    rho: float
    futility: Futility | None
    primary: bool = False
    note: str = ""

    @property
    def arms(self) -> tuple[str, str]:
        return self.better, self.than


@dataclass(frozen=True)
class Plan:
    path: Path
    hash: str  # sha256 of the file's bytes
    preset: str | None
    fixed: dict[str, Any]
    arms: dict[str, dict[str, Any]]  # name -> overrides (insertion order: the plan's)
    seeds: list[int]
    batch: int
    level: float
    multiplicity: str
    claims: list[Claim]
    commit: str | None = None
    name: str = ""
    metric: str = "final_success"
    test: str = "rank-sum"
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def dir(self) -> Path:
        return self.path.parent

    @property
    def max_seeds(self) -> int:
        return len(self.seeds)

    @property
    def max_looks(self) -> int:
        return len(self.seeds) // self.batch

    @property
    def primary(self) -> Claim:
        return next(c for c in self.claims if c.primary)

    def overrides(self, arm: str, seed: int) -> dict[str, Any]:
        return {**self.fixed, **self.arms[arm], "seed": seed}

    def run_name(self, arm: str, seed: int) -> str:
        return f"{arm}-s{seed}"


def file_hash(path: Path) -> str:
    return "sha256:" + hashlib.sha256(path.read_bytes()).hexdigest()


def _seeds(value: Any, where: str) -> list[int]:
    bad = MCRLError(f"{where}: seeds {value!r}: give a list of seeds in the order they run, or FIRST..LAST "
                    "(e.g. 1000..1035)")
    if isinstance(value, str):
        m = re.fullmatch(r"\s*(\d+)\s*\.\.\s*(\d+)\s*", value)
        if not m or int(m.group(2)) < int(m.group(1)):
            raise bad
        return list(range(int(m.group(1)), int(m.group(2)) + 1))
    if not isinstance(value, list) or not value or not all(isinstance(s, int) and not isinstance(s, bool)
                                                           and s >= 0 for s in value):
        raise bad
    if len(set(value)) != len(value):
        raise MCRLError(f"{where}: seeds repeat a seed: list each seed once")
    return list(value)


def _level(value: Any, what: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < float(value) < 0.5:
        raise MCRLError(f"{where}: {what} {value!r} must be a number in (0, 0.5), e.g. 0.05")
    return float(value)


def _spending(value: Any, what: str, where: str) -> str:
    if value not in SPENDING:
        raise MCRLError(f"{where}: {what} {value!r}: choose one of {', '.join(SPENDING)}")
    return value


def _rho(doc: dict, spending: str, where: str) -> float:
    rho = doc.get("rho", 1.0)
    if isinstance(rho, bool) or not isinstance(rho, (int, float)) or rho <= 0:
        raise MCRLError(f"{where}: rho {rho!r} must be a positive number (power spending level * t^rho)")
    if "rho" in doc and spending != "power":
        raise MCRLError(f"{where}: rho is for spending: power only; drop it or use spending: power")
    return float(rho)


def _futility(doc: Any, where: str) -> Futility | None:
    if doc is None:
        return None
    if not isinstance(doc, dict):
        raise MCRLError(f"{where}: futility must be a mapping {{beta, spending, effect}} or absent")
    unknown = sorted(set(doc) - set(FUTILITY_KEYS))
    if unknown:
        raise MCRLError(f"{where}: unknown futility key(s) {unknown}: use {', '.join(FUTILITY_KEYS)}")
    missing = [k for k in ("beta", "effect") if k not in doc]
    if missing:
        raise MCRLError(f"{where}: futility needs {' and '.join(missing)} (beta: the error spent for stopping early "
                        "under the planning effect; effect: the planning P(X > Y))")
    beta = doc["beta"]
    if isinstance(beta, bool) or not isinstance(beta, (int, float)) or not 0 < beta < 1:
        raise MCRLError(f"{where}: futility beta {beta!r} must be in (0, 1), e.g. 0.15")
    eff = doc["effect"]
    if isinstance(eff, bool) or not isinstance(eff, (int, float)) or not 0.5 < eff < 1:
        raise MCRLError(f"{where}: futility effect {eff!r} is the planning P(X > Y): give a number in (0.5, 1)")
    spending = _spending(doc.get("spending", "pocock"), "futility spending", where)
    return Futility(float(beta), spending, _rho(doc, spending, where + " futility"), float(eff))


def _claim(doc: Any, i: int, arms: dict, where: str) -> Claim:
    at = f"{where}: claim {i + 1}"
    if not isinstance(doc, dict):
        raise MCRLError(f"{at} must be a mapping with name, better, than, level")
    unknown = sorted(set(doc) - set(CLAIM_KEYS))
    if unknown:
        raise MCRLError(f"{at}: unknown key(s) {unknown}: use {', '.join(CLAIM_KEYS)}")
    name = doc.get("name")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise MCRLError(f"{at}: name {name!r}: give a short name of letters, digits, '.', '_' or '-'")
    at = f"{where}: claim {name}"
    for key in ("better", "than"):
        if doc.get(key) not in arms:
            raise MCRLError(f"{at}: {key} {doc.get(key)!r} is not an arm: choose one of {', '.join(arms)}")
    if doc["better"] == doc["than"]:
        raise MCRLError(f"{at}: better and than are the same arm: compare two different arms")
    spending = _spending(doc.get("spending", "pocock"), "spending", at)
    primary = doc.get("primary", False)
    if not isinstance(primary, bool):
        raise MCRLError(f"{at}: primary must be true or false")
    return Claim(name, doc["better"], doc["than"], _level(doc.get("level"), "level", at), spending,
                 _rho(doc, spending, at), _futility(doc.get("futility"), at), primary, str(doc.get("note", "")))


def load_plan(path: str | Path) -> Plan:
    """Read and validate a plan file; every problem is one MCRLError naming it and the fix. Does not check the
    arms' configs (`mcrl.decide.runner` resolves them with `resolve_config` before anything runs)."""
    p = Path(path)
    if p.is_dir():
        p = p / "plan.yaml"
    if not p.is_file():
        raise MCRLError(f"plan {path} not found: give the plan.yaml of a sequential experiment (docs/decide.md)")
    where = str(p)
    try:
        doc = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        raise MCRLError(f"{where} is not valid YAML{f' at line {mark.line + 1}' if mark else ''}: fix its syntax") \
            from None
    if not isinstance(doc, dict):
        raise MCRLError(f"{where} must be a YAML mapping with preset, arms, seeds, batch, level and claims")
    unknown = sorted(set(doc) - set(PLAN_KEYS))
    if unknown:
        raise MCRLError(f"{where}: unknown key(s) {unknown}: use {', '.join(PLAN_KEYS)}")
    for key in ("arms", "seeds", "batch", "level", "claims"):
        if key not in doc:
            raise MCRLError(f"{where} has no {key}: a sequential plan fixes arms, seeds, batch, level and claims")
    preset = doc.get("preset")
    if preset is not None and not isinstance(preset, str):
        raise MCRLError(f"{where}: preset must be a preset name (`mcrl presets`)")
    fixed = doc.get("set") or {}
    arms = doc["arms"]
    if not isinstance(fixed, dict):
        raise MCRLError(f"{where}: set must be a mapping of config keys, e.g. set: {{total_steps: 150000}}")
    if not isinstance(arms, dict) or len(arms) < 2:
        raise MCRLError(f"{where}: arms must map at least two arm names to their overrides, "
                        "e.g. arms: {sac: {intrinsic_alpha: 0}, sacmc: {intrinsic_alpha: 0.2}}")
    for name, ov in arms.items():
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
            raise MCRLError(f"{where}: arm name {name!r}: use letters, digits, '.', '_' or '-' (it names run "
                            "directories)")
        if ov is not None and not isinstance(ov, dict):
            raise MCRLError(f"{where}: arm {name}: give a mapping of config overrides (or {{}})")
        if ov and "seed" in ov:
            raise MCRLError(f"{where}: arm {name}: seeds come from the plan's seeds list: remove seed")
    if "seed" in fixed:
        raise MCRLError(f"{where}: set: seeds come from the plan's seeds list: remove seed")
    arms = {k: dict(v or {}) for k, v in arms.items()}
    seeds = _seeds(doc["seeds"], where)
    batch = doc["batch"]
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise MCRLError(f"{where}: batch {batch!r} must be a positive number of seeds an arm per look")
    if len(seeds) % batch:
        raise MCRLError(f"{where}: {len(seeds)} seeds are not a whole number of batches of {batch}: "
                        f"list {len(seeds) // batch * batch} or {(len(seeds) // batch + 1) * batch} seeds")
    level = _level(doc["level"], "level", where)
    multiplicity = doc.get("multiplicity", "holm")
    if multiplicity not in MULTIPLICITY:
        raise MCRLError(f"{where}: multiplicity {multiplicity!r}: choose holm (a confirmed claim's level passes to "
                        "the others) or bonferroni (each claim keeps its share)")
    metric, test = doc.get("metric", METRICS[0]), doc.get("test", TESTS[0])
    if metric not in METRICS:
        raise MCRLError(f"{where}: metric {metric!r}: choose {', '.join(METRICS)}")
    if test not in TESTS:
        raise MCRLError(f"{where}: test {test!r}: choose {', '.join(TESTS)}")
    claims_doc = doc["claims"]
    if not isinstance(claims_doc, list) or not claims_doc:
        raise MCRLError(f"{where}: claims must be a non-empty list")
    claims = [_claim(c, i, arms, where) for i, c in enumerate(claims_doc)]
    names = [c.name for c in claims]
    if len(set(names)) != len(names):
        raise MCRLError(f"{where}: two claims are named alike: give each claim its own name")
    primaries = [c.name for c in claims if c.primary]
    if len(primaries) != 1:
        raise MCRLError(f"{where}: {len(primaries)} claims are marked primary: mark exactly one `primary: true`")
    total = sum(c.level for c in claims)
    if total > level + 1e-12:
        raise MCRLError(f"{where}: the claims' levels add up to {total:g}, above the family's level {level:g}: "
                        "split the level among the claims")
    unused = sorted(set(arms) - {a for c in claims for a in c.arms})
    if unused:
        raise MCRLError(f"{where}: arm(s) {unused} are in no claim: remove them or add their claim")
    commit = doc.get("commit")
    if commit is not None and not (isinstance(commit, str) and re.fullmatch(r"[0-9a-f]{7,40}", commit)):
        raise MCRLError(f"{where}: commit {commit!r} must be a git commit hash")
    return Plan(p, file_hash(p), preset, dict(fixed), arms, seeds, batch, level, multiplicity, claims, commit,
                str(doc.get("name") or p.parent.name), metric, test,
                {k: doc[k] for k in ("description",) if k in doc})
