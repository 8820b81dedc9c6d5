"""One run as ``mcrl report`` reads it: where it lives, what it was told, and what it has written so far."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mcrl.analysis.plots import has_data
from mcrl.files import number


@dataclass
class Run:
    """One run (of the sweep, or a reference arm) and what it has written so far."""

    name: str
    config_key: str | None  # sweep.json's label of its configuration; None for runs from elsewhere
    seed: int | None
    dir: Path
    status: Literal["finished", "partial", "missing"]
    config: dict[str, Any] = field(default_factory=dict)
    overrides: dict[str, Any] = field(default_factory=dict)
    eval: dict[str, np.ndarray] = field(default_factory=dict)
    metrics: dict[str, np.ndarray] = field(default_factory=dict)
    final_eval: dict[str, Any] = field(default_factory=dict)  # final_eval.json; {} when absent
    peer: dict[str, Any] | None = None  # peer.json of a run trained by another system
    source: Path | None = None  # the experiment or directory it was read from
    label: str | None = None  # the user's name for its arm (`mcrl report --with DIR=LABEL`)

    @property
    def has_eval(self) -> bool:
        return has_data(self.eval, "step") and has_data(self.eval, "success_rate")

    @property
    def _final_from_json(self) -> bool:
        return number(self.final_eval.get("mean_return"), finite=True) is not None

    @property
    def final(self) -> tuple[float, float] | None:
        """(success rate, mean return) of the final evaluation, for finished runs only.

        From final_eval.json when the run wrote one (its many-episode evaluation), else from the last
        row of eval.csv.
        """
        if self.status != "finished":
            return None
        if self._final_from_json:
            s = number(self.final_eval.get("success_rate"), finite=True)
            return (math.nan if s is None else s), float(self.final_eval["mean_return"])
        if not self.has_eval:
            return None
        ret = self.eval.get("mean_return", np.array([math.nan]))
        return float(self.eval["success_rate"][-1]), float(ret[-1])

    @property
    def final_source(self) -> tuple[str, int | None] | None:
        """Where :attr:`final` comes from: ("final_eval.json" | "eval.csv", episodes if known)."""
        if self.final is None:
            return None
        if self._final_from_json:
            n = number(self.final_eval.get("episodes"), finite=True)
        else:
            eps = self.eval.get("episodes")
            n = float(eps[-1]) if eps is not None and eps.size and np.isfinite(eps[-1]) else None
        return ("final_eval.json" if self._final_from_json else "eval.csv"), (None if n is None else int(n))

    @property
    def last_step(self) -> float | None:
        steps = [c["step"][np.isfinite(c["step"])] for c in (self.eval, self.metrics) if "step" in c]
        steps = [s for s in steps if s.size]
        return float(max(s.max() for s in steps)) if steps else None

    @property
    def total_steps(self) -> int | None:
        v = self.config.get("total_steps", self.overrides.get("total_steps"))
        return int(v) if v is not None else None
