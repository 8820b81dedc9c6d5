"""The intrinsic weight's schedule: the alpha of `(1 - alpha) r_ext + alpha r_int` as training goes on.

    constant  alpha_t = a                                    (the default: every run before issue 67)
    linear    alpha_t = a (1 - f) + a_end f,  f = min(t / T, 1)   T = intrinsic_schedule_steps, or total_steps
    success   alpha_t = a (1 - s_t)                          s_t the mean success of the last W training episodes

a is `intrinsic_alpha`, a_end `intrinsic_alpha_end`, W `intrinsic_success_window`, t the env step whose gradient
step the weight is for (1 for the first). s_t is 0 before the first episode ends: a run starts at a.

A schedule depends only on host data (the step count, the training episodes' success flags), so its value is a
pure function here, computed on the host, and the jitted gradient step takes the weight as an input
(`mcrl.algo.sac.Mix`): a new alpha each step compiles nothing, and a vmapped group's runs may follow different
schedules. Its state (the success window) is JSON in a checkpoint's meta.json, so a resumed run follows the
same alpha sequence. No JAX here.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from mcrl.config import SCHEDULES, Config

__all__ = ["SCHEDULES", "Schedule"]


@dataclass(frozen=True)
class Schedule:
    """One run's schedule (`Schedule.of(cfg)`); its state is the tuple of recent successes `observe` returns."""

    kind: str  # one of SCHEDULES
    alpha: float  # intrinsic_alpha: the weight at the start
    end: float = 0.0  # linear: the weight from step `steps` on
    steps: int = 1  # linear: env steps from `alpha` to `end`
    window: int = 100  # success: training episodes in the average

    @classmethod
    def of(cls, cfg: Config) -> "Schedule":
        steps = cfg.total_steps if cfg.intrinsic_schedule_steps is None else cfg.intrinsic_schedule_steps
        return cls(cfg.intrinsic_schedule, cfg.intrinsic_alpha, cfg.intrinsic_alpha_end, steps,
                   cfg.intrinsic_success_window)

    def value(self, step: int, successes: Sequence[float] = ()) -> float:
        """The weight of the gradient step at env step `step`, given the success flags `observe` kept."""
        if self.kind == "linear":
            f = min(step / self.steps, 1.0)
            # this form is a at f = 0 and a_end at f = 1 exactly (a + (a_end - a) f can miss a_end by a rounding)
            return self.alpha * (1.0 - f) + self.end * f
        if self.kind == "success":
            return self.alpha * (1.0 - (sum(successes) / len(successes) if successes else 0.0))
        return self.alpha  # constant: the config's float itself, so its step's numbers are today's bit for bit

    def observe(self, successes: Sequence[float], success: float | None) -> tuple[float, ...]:
        """The state after a training episode ended with `success` (None: the environment reports none): the last
        `window` flags for `success`, nothing for the schedules that do not read them (a small meta.json)."""
        if self.kind != "success" or success is None:
            return tuple(successes)
        return (*successes, float(success))[-self.window:]
