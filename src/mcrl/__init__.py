"""mcrl: reinforcement learning with morphological computation (MC) as an intrinsic reward.

The public API::

    from mcrl import Config, resolve_config, train, evaluate_run
    cfg = resolve_config("fetchreach-sacmc", {"total_steps": 3000})
    run_dir = train(cfg)
"""
from mcrl.config import PRESETS, Config, resolve_config
from mcrl.errors import MCRLError

__all__ = ["PRESETS", "Config", "MCRLError", "resolve_config", "train", "evaluate_run"]
__version__ = "0.2.0"


def train(config: Config, run_dir=None, progress: bool = True):
    """Train SAC / SAC-MC with `config`; returns the run directory (see docs/run-directory.md)."""
    from mcrl.run.trainer import train as _train
    from mcrl.video.render import record_training_video

    return _train(config, run_dir=run_dir, progress=progress, video=record_training_video)


def evaluate_run(run_dir, episodes: int | None = None, checkpoint: int | None = None) -> dict:
    """Re-evaluate the saved policy of a run; returns {"success_rate", "mean_return", "episodes"}."""
    from mcrl.run.evaluation import evaluate_run as _evaluate_run

    return _evaluate_run(run_dir, episodes=episodes, checkpoint=checkpoint)
