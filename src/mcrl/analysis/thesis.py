"""The thesis' reference numbers (chapter 4), which ``mcrl report`` compares a reproduction with."""

from __future__ import annotations

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
        "caveat": "The thesis also reports alpha 0.4 and 0.6 about equal to SAC and 0.8, 1.0 below it, "
                  "without table values.",
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
# Preset name prefix (lower case) -> THESIS_RESULTS key.
THESIS_PRESET_PREFIXES: dict[str, str] = {"fetchpush": "FetchPush", "antmaze": "AntMaze"}


def thesis_experiment(preset: str) -> str | None:
    """The THESIS_RESULTS key a preset reproduces, by name prefix; None if it matches none."""
    p = preset.lower()
    return next((v for k, v in THESIS_PRESET_PREFIXES.items() if p.startswith(k)), None)
