"""Building a run's learner from its config, and restoring it from a checkpoint."""
from __future__ import annotations

from pathlib import Path

from mcrl.algo import diagnostics, normaliser
from mcrl.algo.diagnostics import Diagnostics
from mcrl.algo.sac import Agent, TrainState
from mcrl.config import Config
from mcrl.envs import EnvSpec, goal_terminated_fn, inspect, make_env
from mcrl.errors import MCRLError
from mcrl.replay import ReplayBuffer
from mcrl.run import checkpoint, rundir


def build(cfg: Config):
    """(env, spec, agent, buffer) for `cfg`; checks the environment and spaces before anything is written."""
    env = make_env(cfg)
    spec = inspect(env, cfg)
    agent = Agent(spec.obs_dim, spec.act_dim, spec.intrinsic_dim, cfg)
    her = spec.uses_her(cfg)
    buffer = ReplayBuffer(cfg.buffer_size, spec.obs_dim, spec.act_dim, her=her, observation_dim=spec.observation_dim,
                          goal_dim=spec.goal_dim, strategy=cfg.her_strategy, k=cfg.her_k,
                          compute_reward=env.unwrapped.compute_reward if her else None,
                          compute_terminated=goal_terminated_fn(env) if her else None, rounding=cfg.her_rounding)
    return env, spec, agent, buffer


def agent_for(cfg: Config) -> tuple[Agent, EnvSpec]:
    env = make_env(cfg)
    try:
        spec = inspect(env, cfg)
    finally:
        env.close()
    return Agent(spec.obs_dim, spec.act_dim, spec.intrinsic_dim, cfg), spec


def restore(cfg: Config, agent: Agent, ckpt: Path) -> tuple[TrainState, dict]:
    """The learner state and meta.json of checkpoint `ckpt` (what evaluating or rendering it needs)."""
    state, _, meta = restore_run(cfg, agent, ckpt)
    return state, meta


def restore_run(cfg: Config, agent: Agent, ckpt: Path) -> tuple[TrainState, Diagnostics, dict]:
    """The learner state, the diagnostics of the log interval in progress and meta.json of checkpoint `ckpt`
    (its normaliser from normaliser.npz; diagnostics start at zero where the checkpoint has none)."""
    meta = checkpoint.load_meta(ckpt)
    template = agent.init(cfg.seed)
    state, diag = checkpoint.restore_state(ckpt, template._replace(norm=None), diagnostics.init(agent.about.metrics))
    if template.norm is not None:
        packed = checkpoint.load_extra(ckpt, "normaliser")
        if packed is None:
            raise MCRLError(f"checkpoint {ckpt} has no normaliser.npz: it is damaged; delete it to fall back to an "
                            "older one")
        try:
            norm = normaliser.unpack(packed, cfg.intrinsic_history_values)
        except (KeyError, ValueError) as e:
            raise MCRLError(f"checkpoint {ckpt}: its normaliser does not fit this config ({e}): resume with "
                            "the run's own config.json") from None
        state = state._replace(norm=norm)
    return state, diag, meta


def load_policy(run_dir: Path | str, checkpoint_step: int | None = None):
    """(config, agent, train state) of a saved run, from its newest checkpoint or the one at a step."""
    cfg = rundir.read_config(run_dir)
    agent, _ = agent_for(cfg)
    state, _ = restore(cfg, agent, checkpoint.find(Path(run_dir), checkpoint_step))
    return cfg, agent, state
