"""The claims registry: every claim the committed reports decide, declared in one file and grouped into one
multiple-comparison family per baseline arm, so a claim gets the same Holm-adjusted p-value in every report that
prints it, whichever of the family's arms that report holds (issue 49).

Format (YAML, ``claims.yaml``; directories relative to the file)::

    arms:                               # named arms: the runs of a directory, optionally selected by settings
      mcrl SAC: {dir: reproduction/fetchpush/main, select: {intrinsic_alpha: 0}}
      SB3 SAC: {dir: reproduction/fetchpush/sb3-sac}
      SAC pooled: {pool: [mcrl SAC, SB3 SAC]}      # the seeds of several arms as one arm
    families:
      - baseline: mcrl SAC              # an arm's name, or an arm inline: {name: ..., dir: ..., select: {...}}
        claims:
          - {x: SAC-MC 0.2, is: better, by: 0.23, source: "thesis, Tables 4.2-4.3"}
          - {x: SAC-MC 0.4, is: same, margin: 0.115, source: "thesis, section 4.1.3"}
      - baseline: SAC pooled
        requires: mcrl SAC same as SB3 SAC     # a claim's id: this family is tested only once that one is reproduced
        claims: [...]

``is`` is one of :data:`mcrl.analysis.claims.KINDS`; ``by`` is the claimed size of better / worse (what a refutation
excludes, and the difference the power is computed for), ``margin`` the half-width of 'same'. A claim's ``id``
defaults to "X is Y" (e.g. "SAC-MC 0.4 same as mcrl SAC"). ``select`` compares a run's config.json (completed with
the defaults) key by key; the runs it picks must be one configuration. A new baseline, e.g. a re-run at a new
commit, and its claims are one entry under ``families`` with the arms inline.

A report finds the registry as ``claims.yaml`` in its experiment directory or the nearest directory above it, up to
the repository's root (``MCRL_CLAIMS=FILE`` names one, ``MCRL_CLAIMS=none`` turns it off).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from mcrl.analysis.claims import KINDS
from mcrl.analysis.experiment import read_runs
from mcrl.analysis.grouping import arms, run_settings, same_value
from mcrl.analysis.runs import Run
from mcrl.errors import MCRLError
from mcrl.renames import new_names

REGISTRY = "claims.yaml"
ENV = "MCRL_CLAIMS"


@dataclass(frozen=True)
class ArmSpec:
    """An arm of the registry: (directory, selected settings) for each source; several sources are pooled."""

    name: str
    sources: tuple[tuple[Path, tuple[tuple[str, Any], ...]], ...]

    def where(self, root: Path) -> str:
        """'reproduction/fetchpush/main (intrinsic_alpha=0)' for each source, relative to ``root`` where possible."""
        def one(d: Path, sel: tuple[tuple[str, Any], ...]) -> str:
            try:
                d = d.relative_to(root)
            except ValueError:
                pass
            return f"{d}" + (f" ({', '.join(f'{k}={v}' for k, v in sel)})" if sel else "")
        return " + ".join(one(d, s) for d, s in self.sources)


@dataclass(frozen=True)
class ClaimSpec:
    id: str
    x: ArmSpec
    kind: str
    by: float | None  # better / worse / differs: the claimed size; same: the margin
    source: str  # where the claim comes from (the thesis' table, an issue)


@dataclass(frozen=True)
class FamilySpec:
    baseline: ArmSpec
    claims: tuple[ClaimSpec, ...]
    requires: str | None  # the id of a claim that must be reproduced before this family is tested

    @property
    def name(self) -> str:
        return f"against {self.baseline.name}"


@dataclass(frozen=True)
class Registry:
    path: Path
    families: tuple[FamilySpec, ...]

    def find(self, claim_id: str) -> tuple[FamilySpec, ClaimSpec] | None:
        return next(((f, c) for f in self.families for c in f.claims if c.id == claim_id), None)

    def shown(self, root: Path | None = None) -> str:
        """The registry's path as a report shows it (relative to ``root``, else as given)."""
        try:
            return str(self.path.relative_to(root)) if root else str(self.path)
        except ValueError:
            return str(self.path)


def find_registry(start: Path) -> Path | None:
    """``$MCRL_CLAIMS``, else ``claims.yaml`` in ``start`` or the nearest directory above it, up to and including
    the repository's root (the first directory with ``.git``); None when there is none."""
    env = os.environ.get(ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "none") else Path(env)
    for d in [start.resolve(), *start.resolve().parents]:
        if (d / REGISTRY).is_file():
            return d / REGISTRY
        if (d / ".git").exists():
            return None
    return None


def repo_root(path: Path) -> Path | None:
    """The repository holding ``path`` (the nearest directory above it with ``.git``), to show paths from."""
    return next((d for d in path.resolve().parents if (d / ".git").exists()), None)


def _fail(path: Path, what: str) -> MCRLError:
    return MCRLError(f"{path}: {what}")


def _arm(spec: Any, named: dict[str, Any], path: Path, seen: tuple[str, ...] = ()) -> ArmSpec:
    """An arm from its name or an inline mapping {name, dir, select} / {name, pool}."""
    if isinstance(spec, str):
        if spec not in named:
            raise _fail(path, f"arm {spec!r} is not defined under 'arms': define it, or give it inline as "
                              "{name: ..., dir: ..., select: {...}}")
        if spec in seen:
            raise _fail(path, f"arm {spec!r} pools itself")
        return _arm({"name": spec, **named[spec]}, named, path, (*seen, spec))
    if not isinstance(spec, dict) or not spec.get("name"):
        raise _fail(path, f"an arm must be a name or a mapping with 'name' and 'dir' (or 'pool'), not {spec!r}")
    unknown = set(spec) - {"name", "dir", "select", "pool"}
    if unknown or ("dir" in spec) == ("pool" in spec):
        raise _fail(path, f"arm {spec['name']!r}: give either 'dir' (and optionally 'select') or 'pool'"
                          + (f"; unknown keys {sorted(unknown)}" if unknown else ""))
    if "pool" in spec:
        parts = [_arm(p, named, path, (*seen, str(spec["name"]))) for p in spec["pool"]]
        return ArmSpec(str(spec["name"]), tuple(s for a in parts for s in a.sources))
    select = spec.get("select") or {}
    if not isinstance(select, dict):
        raise _fail(path, f"arm {spec['name']!r}: 'select' must map config keys to values")
    try:
        select = new_names(select)  # a registry written before a rename: today's names
    except MCRLError as e:
        raise _fail(path, f"arm {spec['name']!r}: {e}") from None
    return ArmSpec(str(spec["name"]), (((path.parent / str(spec["dir"])).resolve(), tuple(sorted(select.items()))),))


def _claim(c: Any, baseline: ArmSpec, named: dict[str, Any], path: Path) -> ClaimSpec:
    if not isinstance(c, dict) or "x" not in c or "is" not in c:
        raise _fail(path, f"a claim needs 'x' (an arm) and 'is' ({', '.join(KINDS)}), got {c!r}")
    unknown = set(c) - {"id", "x", "is", "by", "margin", "source"}
    if unknown:
        raise _fail(path, f"claim {c!r}: unknown keys {sorted(unknown)}")
    kind = str(c["is"])
    if kind not in KINDS:
        raise _fail(path, f"claim {c!r}: 'is' must be one of {', '.join(KINDS)}")
    size = c.get("margin") if kind == "same" else c.get("by")
    if kind == "same" and not (isinstance(size, (int, float)) and size > 0):
        raise _fail(path, f"claim {c!r}: a 'same' claim needs a positive 'margin'")
    x = _arm(c["x"], named, path)
    return ClaimSpec(str(c.get("id") or f"{x.name} {kind} {'as' if kind == 'same' else 'from' if kind == 'differs' else 'than'} {baseline.name}"),
                     x, kind, None if size is None else float(size), str(c.get("source") or ""))


def load_registry(path: str | Path) -> Registry:
    """Read and check a claims file; MCRLError names what is wrong."""
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise _fail(p, f"cannot read the claims registry ({type(e).__name__}): fix the file or set "
                       f"{ENV}=none") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("families"), list):
        raise _fail(p, "a claims registry needs a 'families' list (and optionally 'arms')")
    named = doc.get("arms") or {}
    families = []
    for f in doc["families"]:
        if not isinstance(f, dict) or "baseline" not in f or not isinstance(f.get("claims"), list):
            raise _fail(p, f"a family needs 'baseline' and a 'claims' list, got {f!r}")
        base = _arm(f["baseline"], named, p)
        families.append(FamilySpec(base, tuple(_claim(c, base, named, p) for c in f["claims"]),
                                   None if f.get("requires") is None else str(f["requires"])))
    reg = Registry(p.resolve(), tuple(families))
    ids = [c.id for f in reg.families for c in f.claims]
    if len(set(ids)) != len(ids):
        raise _fail(p, f"claim ids must be unique: {sorted({i for i in ids if ids.count(i) > 1})}")
    specs: dict[str, ArmSpec] = {}
    for a in [a for f in reg.families for a in (f.baseline, *(c.x for c in f.claims))]:
        if specs.setdefault(a.name, a) != a:
            raise _fail(p, f"two different arms are named {a.name!r}: give one of them another name")
    bases = [f.baseline.name for f in reg.families]
    if len(set(bases)) != len(bases):
        raise _fail(p, f"one family per baseline arm: merge the families against {sorted({b for b in bases if bases.count(b) > 1})}")
    for f in reg.families:
        if f.requires is not None and reg.find(f.requires) is None:
            raise _fail(p, f"family {f.name!r} requires claim {f.requires!r}, which no family declares")
    return reg


# ------------------------------------------------------------------------------------ the arms' runs


def _selected(r: Run, select: tuple[tuple[str, Any], ...]) -> bool:
    """Whether a started run has the selected settings: its config.json's value of each key, else the default."""
    settings = run_settings(r.config)
    if settings is None:
        return False
    return all(same_value(r.config[k] if k in r.config else settings.get(k), v) for k, v in select)


class ArmRuns:
    """The finished runs of registry arms, each directory read once."""

    def __init__(self) -> None:
        self._dirs: dict[Path, list[Run]] = {}

    def _runs(self, d: Path) -> list[Run]:
        if d not in self._dirs:
            self._dirs[d] = read_runs(d, empty_ok=True) if d.is_dir() else []  # not run yet: an arm with 0 seeds
        return self._dirs[d]

    def runs(self, arm: ArmSpec) -> list[Run]:
        """The finished runs of ``arm``, each source in seed order, sources in the order given."""
        out: list[Run] = []
        for d, select in arm.sources:
            picked = [r for r in self._runs(d) if r.final is not None and _selected(r, select)]
            if len(arms(picked)) > 1:
                raise MCRLError(f"arm {arm.name!r} of the claims registry selects runs of {len(arms(picked))} "
                                f"configurations in {d}: add the settings that tell them apart to its 'select'")
            out += sorted(picked, key=lambda r: (r.seed is None, r.seed or 0, r.name))
        return out

    def dirs(self, arm: ArmSpec) -> frozenset[Path]:
        """Where its finished runs live: a report's arm with exactly these runs is this arm."""
        return frozenset(r.dir.resolve() for r in self.runs(arm))
