"""Environment construction and the observation / action / success conventions mcrl relies on."""
from __future__ import annotations

import dataclasses
import tempfile
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from mcrl.config import Config
from mcrl.errors import MCRLError

GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")
_registered = False


@dataclass(frozen=True)
class EnvFamily:
    """What mcrl knows about a family of environments without making one (so reports need no simulator)."""

    name: str
    prefix: str  # environment ids starting with it belong to the family (the longest matching prefix wins)
    success_key: str  # the `info` key of its success flag
    reward_max: float  # the largest per-step extrinsic reward: the critics' divergence bound (analysis.divergence)
    act_dim: int  # its action dimension
    example: str  # one registered id of it (tests check the facts above against it)
    thesis_table: str | None = None  # the thesis table its runs are compared with (mcrl.analysis.thesis)


# Fetch: sparse -1/0 (or dense -distance) reward, 4-d actions, `is_success`; the mazes: dense exp(-distance) or
# sparse 0/1, `success`. A new family is one line here.
FAMILIES: tuple[EnvFamily, ...] = (
    EnvFamily("FetchPush", "FetchPush", "is_success", 0.0, 4, "FetchPush-v4", thesis_table="FetchPush"),
    EnvFamily("Fetch", "Fetch", "is_success", 0.0, 4, "FetchReach-v4"),
    EnvFamily("AntMaze", "AntMaze", "success", 1.0, 8, "AntMaze_UMazeDense-v5", thesis_table="AntMaze"),
    EnvFamily("PointMaze", "PointMaze", "success", 1.0, 2, "PointMaze_UMaze-v3"),
)
SUCCESS_KEYS = tuple(dict.fromkeys(f.success_key for f in FAMILIES))  # read in this order from any env's info


def family_of(env_id: str) -> EnvFamily | None:
    """The family of an environment id, or None for an environment mcrl knows nothing particular about."""
    fams = [f for f in FAMILIES if str(env_id).startswith(f.prefix)]
    return max(fams, key=lambda f: len(f.prefix)) if fams else None


def register_envs() -> None:
    """Register gymnasium-robotics' environments (once, quietly)."""
    global _registered
    if not _registered:
        import contextlib
        import io

        # gymnasium_robotics prints a notice about Adroit environments on import
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            import gymnasium_robotics
        gym.register_envs(gymnasium_robotics)
        _registered = True


@dataclass(frozen=True)
class EnvSpec:
    """What the learner needs to know about an environment."""

    goal_env: bool
    obs_dim: int  # flat policy input
    act_dim: int
    observation_dim: int  # the `observation` part (goal envs) or the whole Box
    goal_dim: int  # 0 for Box envs
    intrinsic_dim: int  # the intrinsic state: first intrinsic_dim entries of the flat obs
    max_episode_steps: int | None

    def uses_her(self, cfg: Config) -> bool:
        """HER is on when asked for, or by default for goal-conditioned Dict environments."""
        return self.goal_env if cfg.her is None else bool(cfg.her)


def resolve_env_id(cfg: Config) -> Config:
    """`cfg` with the id gymnasium makes for its `env_id`: an id without a version (FetchReach) is the newest version
    registered (FetchReach-v4), as `gym.make` picks it, so config.json names the environment that ran, not one a
    later release may change. An id gymnasium does not know is left as given, for `make_env` to refuse."""
    from gymnasium.envs.registration import find_highest_version, get_env_id, parse_env_id

    register_envs()
    if cfg.env_id in gym.registry:
        return cfg
    try:
        ns, name, version = parse_env_id(cfg.env_id)
    except gym.error.Error:
        return cfg
    latest = find_highest_version(ns, name) if version is None else None
    return cfg if latest is None else dataclasses.replace(cfg, env_id=get_env_id(ns, name, latest))


def make_env(cfg: Config, render_mode: str | None = None) -> gym.Env:
    register_envs()
    try:
        env = gym.make(cfg.env_id, render_mode=render_mode, **cfg.env_kwargs)
    except (gym.error.DependencyNotInstalled, ImportError) as e:  # registered, but needs a package (or version)
        raise MCRLError(f"environment {cfg.env_id!r} cannot be made here: {_one_line(e)}: install what it names, "
                        "or pick another environment") from None
    except gym.error.Error as e:  # NameNotFound, VersionNotFound, ...
        raise MCRLError(f"unknown environment {cfg.env_id!r} ({_one_line(e)}): give a registered gymnasium id, "
                        "e.g. FetchPush-v4 or AntMaze_UMazeDense-v5") from None
    except TypeError as e:
        raise MCRLError(f"environment {cfg.env_id!r} rejected env_kwargs {cfg.env_kwargs}: {_one_line(e)}") from None
    remove_maze_xml(env)
    return env


def remove_maze_xml(env: gym.Env) -> None:
    """gymnasium-robotics' mazes (AntMaze, PointMaze) write their model to a new file in the temporary directory
    each time one is made and never remove it: a training run makes two, a sweep thousands. MuJoCo has read it by
    now, and nothing reads it again."""
    path = getattr(env.unwrapped, "tmp_xml_file_path", None)
    if isinstance(path, str) and Path(path).parent == Path(tempfile.gettempdir()):
        Path(path).unlink(missing_ok=True)


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


def inspect(env: gym.Env, cfg: Config) -> EnvSpec:
    """Check the spaces and return their sizes; raises MCRLError naming the fix."""
    if not isinstance(env.action_space, gym.spaces.Box):
        raise MCRLError(f"{cfg.env_id} has a {type(env.action_space).__name__} action space: SAC needs a "
                        "continuous Box action space")
    act_dim = int(np.prod(env.action_space.shape))
    space = env.observation_space
    goal_env = isinstance(space, gym.spaces.Dict) and all(k in space.spaces for k in GOAL_KEYS)
    if cfg.her and not goal_env:
        raise MCRLError(f"her=true but {cfg.env_id} has no observation/achieved_goal/desired_goal Dict "
                        "observation: set --set her=false")
    if goal_env:
        nested = [k for k in GOAL_KEYS if not isinstance(space[k], gym.spaces.Box)]
        if nested:
            raise MCRLError(f"{cfg.env_id}'s {' and '.join(nested)} are {type(space[nested[0]]).__name__} spaces, "
                            "not Boxes: mcrl's HER needs flat goal vectors; wrap the environment in a gymnasium "
                            "ObservationWrapper that flattens them (gymnasium.spaces.flatten) and pass its id")
        od = int(np.prod(space["observation"].shape))
        gd = int(np.prod(space["desired_goal"].shape))
        obs_dim = od + 2 * gd
    elif isinstance(space, gym.spaces.Box):
        od, gd, obs_dim = int(np.prod(space.shape)), 0, int(np.prod(space.shape))
    else:
        raise MCRLError(f"{cfg.env_id} has a {type(space).__name__} observation space: mcrl needs a Box or a "
                        "goal Dict (observation, achieved_goal, desired_goal)")
    intrinsic_dim = obs_dim if cfg.intrinsic_state == "full" else od
    steps = env.spec.max_episode_steps if env.spec is not None else None
    return EnvSpec(goal_env, obs_dim, act_dim, od, gd, intrinsic_dim, steps)


def flatten_obs(obs) -> np.ndarray:
    """Policy input: observation | achieved_goal | desired_goal for goal envs, the Box itself otherwise."""
    if isinstance(obs, dict):
        return np.concatenate([np.asarray(obs[k], np.float32).reshape(-1) for k in GOAL_KEYS])
    return np.asarray(obs, np.float32).reshape(-1)


def to_env_action(action: np.ndarray, env: gym.Env, action_scale: float) -> np.ndarray:
    """Policy actions live in [-1, 1]; scale them, then map onto the Box's bounds."""
    low, high = env.action_space.low, env.action_space.high
    a = np.clip(np.asarray(action, np.float64) * action_scale, -1.0, 1.0)
    if np.all(np.isfinite(low)) and np.all(np.isfinite(high)):
        a = low + (a + 1.0) * 0.5 * (high - low)
    return a.astype(env.action_space.dtype).reshape(env.action_space.shape)


def goal_terminated_fn(env: gym.Env):
    """`terminated` of transitions under new goals: (achieved (n, g), desired (n, g)) -> (n,) float32, or None.

    HER relabels goals; an environment that ends episodes on success (AntMaze or PointMaze with
    continuing_task=False) must then get `terminated` recomputed for the new goal, as its reward is.
    gymnasium-robotics' `compute_terminated` takes one transition at a time (the maze's takes the norm of
    the whole array), so it is called row by row.
    """
    fn = getattr(env.unwrapped, "compute_terminated", None)
    if fn is None:
        return None

    def terminated(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return np.fromiter((bool(fn(a, d, {})) for a, d in zip(achieved, desired)), np.float32, len(achieved))

    return terminated


def success_of(info: dict) -> float | None:
    """Success flag the environment reports (`is_success` for Fetch, `success` for the mazes: FAMILIES), if any."""
    for k in SUCCESS_KEYS:
        if k in info:  # a numpy scalar or a 1-element array, depending on the environment
            return float(np.asarray(info[k], dtype=np.float64).reshape(-1)[0])
    return None


def episode_seed(seed: int, stream: int, episode: int) -> int:
    """Seed of every reset: runs are reproducible and resumable without saving the env's RNG."""
    return int(np.random.SeedSequence([seed, stream, episode]).generate_state(1)[0])
