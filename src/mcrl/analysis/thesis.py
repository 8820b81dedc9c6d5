"""The thesis' reference numbers and claims (chapter 4), which ``mcrl report`` compares a reproduction with."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

# Thesis chapter 4 (Tables 4.2-4.5; /work/shared/FACTS.md). "variance" is the thesis' "Variance of
# Success Rate" (its definition is not stated there); "mean_reward" its "Mean Reward", which in
# range matches a mean evaluation-episode return (FetchPush: 50 steps of -1/0).
THESIS_RESULTS: dict[str, dict[str, Any]] = {
    "FetchPush": {
        "tables": "Tables 4.2 and 4.3",
        "total_steps": 150_000,
        "seeds": 6,
        "by_alpha": {
            0.0: {"success_mean": 0.52, "success_var": 0.2, "mean_reward": -31.3},
            0.2: {"success_mean": 0.75, "success_var": 0.2, "mean_reward": -23.0},
        },
        # Section 4.1.3 gives the other alphas in words (and two mean rewards, printed without their sign:
        # "a mean reward of 28.81 and 28.96"; FetchPush's returns lie in [-50, 0]). "claim" is what each says
        # against SAC, tested as a 'same' or 'worse' claim (mcrl.analysis.claims).
        "alpha_curve": {
            0.4: {"claim": "same", "mean_reward": -28.81,
                  "words": "the success rate ... becomes comparable to that of the baseline SAC algorithm; "
                           "the performance in terms of average reward converges with that of the baseline SAC "
                           "with a mean reward of 28.81"},
            0.6: {"claim": "same", "mean_reward": -28.96,
                  "words": "the success rate ... becomes comparable to that of the baseline SAC algorithm; "
                           "... converges with that of the baseline SAC with a mean reward of ... 28.96"},
            0.8: {"claim": "worse",
                  "words": "at 80% and 100% morphological computation, the Success rate and the average rewards "
                           "decrease; the success rates observed for both SAC-MC 0.8 & 1.0 models are "
                           "relatively low"},
            1.0: {"claim": "worse",
                  "words": "at 80% and 100% morphological computation, the Success rate and the average rewards "
                           "decrease; the success rates observed for both SAC-MC 0.8 & 1.0 models are "
                           "relatively low"},
        },
        "caveat": "Beyond alpha 0.2 the thesis gives words and two mean rewards, no table: the alpha-curve "
                  "subsection tests its words (0.4 and 0.6 about equal to SAC, 0.8 and 1.0 below it).",
    },
    "AntMaze": {
        "tables": "Tables 4.4 and 4.5",
        "total_steps": 400_000,
        "seeds": 4,
        "by_alpha": {
            0.0: {"success_mean": 0.38, "success_var": 0.14, "mean_reward": 155.3},
            0.2: {"success_mean": 0.52, "success_var": 0.16, "mean_reward": 206.5},
        },
        "caveat": "The thesis ran its own AntGym maze (action scale 0.4, map not recoverable from the "
                  "text); mcrl's dense UMaze is a public stand-in, so the task itself differs.",
    },
}
def thesis_experiment(preset: str | None, env_ids: Iterable[str] = ()) -> str | None:
    """The THESIS_RESULTS key an experiment is compared with: the thesis table of its environment family
    (mcrl.envs.FAMILIES; the runs' `env_ids`, else the preset's own environment), for a preset named after that
    table (fetchpush-*, antmaze-*); None for any other preset, or runs of several families or of none with a table."""
    from mcrl.config import PRESETS
    from mcrl.envs import family_of

    envs = set(env_ids) or ({PRESETS[preset][1].get("env_id", "")} if preset in PRESETS else set())
    fams = {family_of(e) for e in envs}
    fam = fams.pop() if len(fams) == 1 else None
    if fam is None or fam.thesis_table not in THESIS_RESULTS:
        return None
    return fam.thesis_table if str(preset or "").lower().startswith(fam.thesis_table.lower()) else None


def env_ids(runs: Iterable[Any]) -> set[str]:
    """The environments of runs (objects with a `config` dict), for `thesis_experiment`."""
    return {str(r.config["env_id"]) for r in runs if "env_id" in r.config}


def thesis_gain(name: str | None) -> float | None:
    """The thesis' gain in mean success of SAC-MC alpha 0.2 over SAC (FetchPush +0.23), exact to the table's two
    decimals (0.75 - 0.52 is 0.22999999999999998 in floating point); None for an experiment it does not have."""
    t = THESIS_RESULTS.get(name or "")
    if t is None:
        return None
    return round(t["by_alpha"][0.2]["success_mean"] - t["by_alpha"][0.0]["success_mean"], 9)


def equivalence_margin(name: str | None) -> float | None:
    """The margin of the thesis' "about the same as SAC": half its SAC-MC 0.2 lead (FetchPush 0.115). A difference
    under half that lead is nearer SAC than SAC-MC 0.2, the contrast the thesis draws; its own mean rewards at 0.4
    and 0.6 (-28.81, -28.96) lie 0.29-0.30 of the way from SAC's -31.3 to SAC-MC 0.2's -23."""
    gain = thesis_gain(name)
    return None if gain is None else round(gain / 2, 9)
