"""Typed run configuration and the presets named after the thesis' experiments.

A run is fully described by one `Config`. Presets reproduce the thesis' hyperparameter tables
(Appendix A and C); anything can be overridden with ``--set key=value`` on the command line or a
dict in Python. `resolve_config` validates the result, so a bad value fails before anything runs.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

import yaml

from mcrl.algo import intrinsic as intrinsic_rewards
from mcrl.errors import MCRLError
from mcrl.renames import new_names, trained_config


@dataclass
class Config:
    # --- task ---
    env_id: str = "FetchReach-v4"
    env_kwargs: dict = field(default_factory=dict)
    action_scale: float = 1.0  # policy actions in [-1, 1] are multiplied by this, then mapped to the Box
    total_steps: int = 5_000
    seed: int = 0
    # --- SAC (thesis Appendix A) ---
    learning_rate: float = 3e-4
    buffer_size: int = 1_000_000
    batch_size: int = 256
    tau: float = 0.005
    gamma: float = 0.99
    hidden_sizes: tuple[int, ...] = (256, 256, 256)
    learning_starts: int = 100  # random-action warm-up steps (stable-baselines3's default)
    ent_coef_init: float = 1.0  # 'auto' entropy coefficient, initial value (stable-baselines3's default)
    target_entropy: float | None = None  # None = -|A|
    init: str = "torch"  # torch: weights and biases ~ U(+-1/sqrt(fan_in)) like torch's Linear | flax: LeCun normal, zero bias
    squash_correction: str = "exact"  # exact: log(1 - tanh(u)^2) | epsilon: log(1 - a^2 + 1e-6), as SB3 and the thesis' code
    matmul_precision: str = "float32"  # float32 | bfloat16: layer inputs and kernels rounded to bfloat16 for the
    # matmuls, with float32 accumulation; parameters and everything else stay float32
    # --- HER ---
    her: bool | None = None  # None = on for goal-conditioned Dict environments
    her_strategy: str = "future"  # future | final | episode
    her_k: int = 4  # sampled goals per real transition: relabel fraction k / (k + 1)
    her_rounding: str = "nearest"  # relabelled rows of a batch: nearest round(B k/(k+1)) = 205 of 256 | floor: int(),
    # 204 of 256, as stable-baselines3's HerReplayBuffer (the thesis' code's buffer)
    # --- the intrinsic reward (docs/intrinsic.md); renamed keys were mc_* before (`mcrl.renames`) ---
    intrinsic: str = intrinsic_rewards.THESIS_REWARD  # the reward intrinsic_alpha mixes in: a name of
    # mcrl.algo.intrinsic's registry; by default the thesis' MC
    intrinsic_alpha: float = 0.0  # its weight: (1 - a) r_ext + a r_int; with a schedule, the weight at the start
    intrinsic_schedule: str = "constant"  # how the weight moves in training: constant | linear | success
    intrinsic_alpha_end: float = 0.0  # linear: the weight it ends at
    intrinsic_schedule_steps: int | None = None  # linear: env steps to reach intrinsic_alpha_end; None = total_steps
    intrinsic_success_window: int = 100  # success: training episodes of the success average s, weight a (1 - s)
    intrinsic_models: bool | None = None  # None = train the reward's models iff intrinsic_alpha > 0
    intrinsic_lr: float = 3e-4
    intrinsic_hidden_sizes: tuple[int, ...] = (256, 256, 256, 256, 256)
    intrinsic_state: str = "observation"  # observation | full (observation + achieved_goal + desired_goal)
    mc_reduction: str = "transition"  # MC only: transition (thesis text) | batch (thesis code: one batch-mean KL)
    intrinsic_history: int | None = None  # gradient steps of raw values the normaliser keeps; None = the whole run
    min_percentile: float = 0.0
    max_percentile: float = 94.0
    intrinsic_reward_low: float = -1.0
    intrinsic_reward_high: float = 0.0
    # --- evaluation, logging, checkpoints ---
    eval_every: int = 2_500
    eval_episodes: int = 10
    final_eval_episodes: int | None = None  # episodes of the evaluation at the end (None = eval_episodes)
    log_every: int = 500
    checkpoint_every: int = 10_000  # env steps; a checkpoint is written at the next episode end
    keep_checkpoints: int = 2
    save_buffer: bool = True
    video_every: int = 0  # record an evaluation video every N steps (0 = never)
    out_dir: str = "runs"
    preset: str | None = None

    # ---- derived ----
    @property
    def intrinsic_alpha_max(self) -> float:
        """The largest weight the schedule can give (linear may rise from intrinsic_alpha to intrinsic_alpha_end)."""
        return max(self.intrinsic_alpha, self.intrinsic_alpha_end if self.intrinsic_schedule == "linear" else 0.0)

    @property
    def use_intrinsic_models(self) -> bool:
        """Whether this run trains the models of its intrinsic reward (SAC runs do not, unless asked)."""
        return self.intrinsic_alpha_max > 0 if self.intrinsic_models is None else bool(self.intrinsic_models)

    @property
    def intrinsic_values_per_step(self) -> int:
        """Raw values one gradient step adds to the normaliser's history, as its reward's `About` says (MC's batch
        variant: one)."""
        return intrinsic_rewards.about(self.intrinsic).values_per_step(self)

    @property
    def intrinsic_history_values(self) -> int | None:
        """Capacity of the normaliser's window in raw values; None = every value of the run."""
        return None if self.intrinsic_history is None else self.intrinsic_history * self.intrinsic_values_per_step

    @property
    def n_final_eval_episodes(self) -> int:
        return self.eval_episodes if self.final_eval_episodes is None else self.final_eval_episodes

    def to_dict(self) -> dict[str, Any]:
        """Every field by its name, as files store it (config.json, meta.json, sweep.json)."""
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Config":
        """A config from keys and values; old names of renamed keys (`mcrl.renames`) are read as today's."""
        d = new_names(d)
        unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise MCRLError(f"unknown config key(s) {sorted(unknown)}: run `mcrl presets --keys` to list valid keys")
        cfg = cls(**{k: _coerce(k, v) for k, v in d.items()})
        validate(cfg)
        return cfg

    @classmethod
    def from_run_json(cls, d: dict[str, Any]) -> "Config":
        """A run directory's config.json; keys added since it was written take their defaults. One that lists
        `mc_history` but no `init` was written by mcrl 0.1 (Flax's initialisation, `mc_history` counted in KL
        values, not gradient steps): refused, not guessed."""
        d = trained_config(d)  # a key added since: the behaviour it was trained with, whatever its default
        if "init" not in d and "intrinsic_history" in d:
            raise MCRLError("this config.json was written by mcrl 0.1 (it has no `init`): convert its run directory "
                            "with `python scripts/migrate_checkpoint.py RUN_DIR` (docs/run-directory.md)")
        return cls.from_dict(d)


# how the intrinsic weight moves during training (mcrl.algo.schedule; docs/intrinsic.md#schedules)
SCHEDULES = ("constant", "linear", "success")

# One line about a key, where its name alone does not say it (`mcrl presets --keys` prints it beside the key).
KEY_NOTES: dict[str, str] = {
    "intrinsic": "the intrinsic reward intrinsic_alpha mixes in: mc (thesis) | rnd | icm | disagreement "
                 "(docs/intrinsic.md), or any other registered in mcrl.algo.intrinsic",
    "intrinsic_alpha": "weight of the intrinsic reward: (1 - a) r_ext + a r_int; 0 = plain SAC",
    "intrinsic_schedule": "how intrinsic_alpha moves in training: constant | linear (to intrinsic_alpha_end over "
                          "intrinsic_schedule_steps) | success (alpha (1 - s), s the training success average)",
    "intrinsic_alpha_end": "linear schedule: the weight it ends at, in [0, 1] (default 0: hand over to the task)",
    "intrinsic_schedule_steps": "linear schedule: env steps from intrinsic_alpha to intrinsic_alpha_end; null = "
                                "total_steps",
    "intrinsic_success_window": "success schedule: training episodes the success average s covers",
    "intrinsic_models": "train the intrinsic reward's models even at intrinsic_alpha=0 (null: iff intrinsic_alpha "
                        "> 0)",
    "intrinsic_lr": "Adam learning rate of the intrinsic reward's models",
    "intrinsic_hidden_sizes": "MC models' hidden layers; rnd/icm/disagreement use their papers' depths at its "
                              "widest width",
    "intrinsic_state": "the state the intrinsic reward sees: observation | full (+ achieved and desired goal)",
    "intrinsic_history": "gradient steps of raw values the normaliser's percentiles cover; null = the whole run",
    "intrinsic_reward_low": "the normalised intrinsic reward's range is [low, high]",
    "intrinsic_reward_high": "the normalised intrinsic reward's range is [low, high]",
    "mc_reduction": "MC only: transition (each transition's KL, thesis text) | batch (one batch-mean KL, its code)",
    "her_rounding": "relabelled rows per batch: nearest round(B k/(k+1)) | floor int(B k/(k+1)), as SB3's buffer",
    "squash_correction": "tanh log-prob correction: exact log(1 - tanh(u)^2) | epsilon log(1 - a^2 + 1e-6) "
                         "(stable-baselines3 and the thesis' code; at most 13.8 nats per action entry)",
}

_FETCHPUSH = dict(env_id="FetchPush-v4", total_steps=150_000, learning_rate=3e-4, buffer_size=1_000_000,
                  batch_size=256, tau=0.005, gamma=0.99, her=True, intrinsic_lr=3e-4, min_percentile=0.0,
                  max_percentile=94.0, intrinsic_reward_low=-1.0, intrinsic_reward_high=0.0, eval_every=5_000,
                  log_every=1_000, final_eval_episodes=100)
# The thesis' framework ran a 27-d ant observation (no contact forces) with actions scaled by 0.4.
_ANTMAZE = dict(env_id="AntMaze_UMazeDense-v5", env_kwargs={"include_cfrc_ext_in_observation": False},
                action_scale=0.4, total_steps=400_000, learning_rate=4e-4, buffer_size=1_000_000,
                batch_size=2048, tau=0.05, gamma=0.95, her=True, intrinsic_lr=4e-4, min_percentile=0.0,
                max_percentile=98.0, intrinsic_reward_low=0.0, intrinsic_reward_high=1.0, eval_every=10_000,
                eval_episodes=10, log_every=2_000, final_eval_episodes=100)
_FETCHREACH = dict(env_id="FetchReach-v4", total_steps=9_000, her=True, intrinsic_lr=3e-4, max_percentile=94.0,
                   intrinsic_reward_low=-1.0, intrinsic_reward_high=0.0, eval_every=1_000, log_every=250)

# name -> (description, overrides of the Config defaults)
PRESETS: dict[str, tuple[str, dict[str, Any]]] = {
    "fetchpush-sac": ("Thesis Table A.1: SAC+HER baseline on FetchPush, 150k steps",
                      {**_FETCHPUSH, "intrinsic_alpha": 0.0}),
    **{
        f"fetchpush-sacmc-{a}": (f"Thesis Table A.2: SAC-MC alpha={a} on FetchPush, 150k steps",
                                 {**_FETCHPUSH, "intrinsic_alpha": float(a)})
        for a in ("0.2", "0.4", "0.6", "0.8", "1.0")
    },
    "antmaze-sac": ("Thesis Table A.3: SAC+HER baseline on AntMaze (dense U-maze), 400k steps",
                    {**_ANTMAZE, "intrinsic_alpha": 0.0}),
    "antmaze-sacmc": ("Thesis Table A.4: SAC-MC alpha=0.2, max percentile 98 on AntMaze, 400k steps",
                      {**_ANTMAZE, "intrinsic_alpha": 0.2}),
    "antmaze-sacmc-p94": ("Thesis Table C.1: SAC-MC alpha=0.2, max percentile 94 on AntMaze, 400k steps",
                          {**_ANTMAZE, "intrinsic_alpha": 0.2, "max_percentile": 94.0}),
    "fetchreach-sac": ("Quick demo: SAC+HER on FetchReach, 9k steps (thesis sizes)",
                       {**_FETCHREACH, "intrinsic_alpha": 0.0}),
    "fetchreach-sacmc": ("Quick demo: SAC-MC alpha=0.2 on FetchReach, 9k steps (thesis sizes)",
                         {**_FETCHREACH, "intrinsic_alpha": 0.2}),
}


def resolve_config(preset: str | None = None, overrides: dict[str, Any] | None = None) -> Config:
    """The preset's values, then `overrides` on top (old key names read as the new ones); validated."""
    d: dict[str, Any] = {}
    if preset is not None:
        if preset not in PRESETS:
            raise MCRLError(f"unknown preset {preset!r}: choose one of {', '.join(PRESETS)} (`mcrl presets`)")
        d.update(PRESETS[preset][1])
        d["preset"] = preset
    d.update(new_names(overrides or {}))
    return Config.from_dict(d)


def parse_set(items: list[str]) -> dict[str, Any]:
    """Parse ``key=value`` strings (values in YAML syntax: 0.2, true, [256, 256], null)."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise MCRLError(f"bad --set {item!r}: write key=value, e.g. --set intrinsic_alpha=0.2")
        k, v = item.split("=", 1)
        try:
            out[k.strip()] = yaml.safe_load(v)
        except yaml.YAMLError:
            out[k.strip()] = v
    return out


_FIELDS = {f.name: f for f in dataclasses.fields(Config)}


def _coerce(key: str, value: Any) -> Any:
    """Convert a parsed value to the field's type, with a one-line error on mismatch."""
    typ = str(_FIELDS[key].type)
    if value is None:
        if "None" in typ:
            return None
        raise MCRLError(f"config key {key!r} cannot be null: give a value of type {typ}")
    try:
        if typ.startswith("tuple"):
            if isinstance(value, (int, float)):
                value = [value]
            return tuple(int(v) for v in value)
        if typ.startswith("bool"):
            if isinstance(value, str):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(value)
                return value.lower() in ("true", "1")
            return bool(value)
        if typ.startswith("int"):
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(value)
            return int(value)
        if typ.startswith("float"):
            return float(value)
        if typ.startswith("dict"):
            if not isinstance(value, dict):
                raise ValueError(value)
            return dict(value)
        if typ.startswith("str"):
            return str(value)
    except (TypeError, ValueError):
        raise MCRLError(f"config key {key!r} got {value!r}: expected {typ}") from None
    return value


def validate(cfg: Config) -> None:
    """Reject values that cannot work, each with a message naming the fix."""
    def bad(msg: str) -> None:
        raise MCRLError(msg)

    if not 0.0 <= cfg.intrinsic_alpha <= 1.0:
        bad(f"intrinsic_alpha={cfg.intrinsic_alpha} is outside [0, 1]: pick a weight between 0 (pure SAC) and 1 "
            "(the intrinsic reward only)")
    for name in ("min_percentile", "max_percentile"):
        v = getattr(cfg, name)
        if not 0.0 <= v <= 100.0:
            bad(f"{name}={v} is outside [0, 100]: percentiles are between 0 and 100")
    if cfg.min_percentile >= cfg.max_percentile:
        bad(f"min_percentile={cfg.min_percentile} >= max_percentile={cfg.max_percentile}: "
            "the lower bound's percentile must be below the upper one (thesis: 0 and 94)")
    if cfg.intrinsic_reward_low >= cfg.intrinsic_reward_high:
        bad(f"intrinsic_reward_low={cfg.intrinsic_reward_low} >= intrinsic_reward_high={cfg.intrinsic_reward_high}: "
            "give a range low < high")
    if cfg.her_strategy not in ("future", "final", "episode"):
        bad(f"her_strategy={cfg.her_strategy!r}: choose future, final or episode")
    if cfg.her_rounding not in ("nearest", "floor"):
        bad(f"her_rounding={cfg.her_rounding!r}: choose nearest (round(B k/(k+1))) or floor (int(), as "
            "stable-baselines3)")
    if cfg.intrinsic_state not in ("observation", "full"):
        bad(f"intrinsic_state={cfg.intrinsic_state!r}: choose observation or full")
    if cfg.mc_reduction not in ("transition", "batch"):
        bad(f"mc_reduction={cfg.mc_reduction!r}: choose transition or batch")
    if not intrinsic_rewards.known(cfg.intrinsic):
        bad(f"intrinsic={cfg.intrinsic!r} is not a registered reward: choose one of "
            f"{', '.join(intrinsic_rewards.names())} (docs/intrinsic.md), or install the package that declares it "
            f"in the entry-point group {intrinsic_rewards.ENTRY_POINTS} (mcrl.algo.intrinsic.register lasts one "
            "process)")
    for key, owner in intrinsic_rewards.owned_keys().items():  # a reward's own key, given for another reward
        default = _FIELDS[key].default if key in _FIELDS else None  # (a key no Config has is nobody's to give)
        if key in _FIELDS and owner != cfg.intrinsic and getattr(cfg, key) != default:
            title = intrinsic_rewards.about(owner).title
            bad(f"{key}={getattr(cfg, key)} is read only by intrinsic={owner} ({title}), not by "
                f"intrinsic={cfg.intrinsic}: drop it ({key}={default})")
    if cfg.init not in ("torch", "flax"):
        bad(f"init={cfg.init!r}: choose torch (as stable-baselines3 and the thesis' code) or flax")
    if cfg.squash_correction not in ("exact", "epsilon"):
        bad(f"squash_correction={cfg.squash_correction!r}: choose exact (log(1 - tanh(u)^2)) or epsilon "
            "(log(1 - a^2 + 1e-6), as stable-baselines3 and the thesis' code)")
    if cfg.matmul_precision not in ("float32", "bfloat16"):
        bad(f"matmul_precision={cfg.matmul_precision!r}: choose float32 (the default) or bfloat16 "
            "(bfloat16 matmul inputs, float32 accumulation and parameters)")
    if cfg.intrinsic_schedule not in SCHEDULES:
        bad(f"intrinsic_schedule={cfg.intrinsic_schedule!r}: choose constant (a fixed weight), linear (intrinsic_alpha "
            "to intrinsic_alpha_end) or success (intrinsic_alpha x (1 - training success)); docs/intrinsic.md")
    if not 0.0 <= cfg.intrinsic_alpha_end <= 1.0:
        bad(f"intrinsic_alpha_end={cfg.intrinsic_alpha_end} is outside [0, 1]: pick the linear schedule's end weight "
            "between 0 (the task's reward only) and 1")
    if cfg.intrinsic_success_window < 1:
        bad(f"intrinsic_success_window={cfg.intrinsic_success_window} must be at least 1: the success schedule "
            "averages that many training episodes, e.g. 100")
    if cfg.intrinsic_schedule_steps is not None and cfg.intrinsic_schedule_steps < 1:
        bad(f"intrinsic_schedule_steps={cfg.intrinsic_schedule_steps} must be at least 1, or null (total_steps)")
    if cfg.intrinsic_alpha_max > 0 and cfg.intrinsic_models is False:
        key = "intrinsic_alpha" if cfg.intrinsic_alpha > 0 else "intrinsic_alpha_end"  # linear may rise from 0
        bad(f"{key}={getattr(cfg, key)} needs the intrinsic reward's models, but intrinsic_models=false: "
            "drop --set intrinsic_models=false (or set intrinsic_alpha=0 for plain SAC)")
    for name in ("total_steps", "batch_size", "buffer_size", "eval_episodes", "log_every",
                 "checkpoint_every", "keep_checkpoints"):
        if getattr(cfg, name) < 1:
            bad(f"{name}={getattr(cfg, name)} must be at least 1")
    for name in ("intrinsic_history", "final_eval_episodes"):
        if getattr(cfg, name) is not None and getattr(cfg, name) < 1:
            bad(f"{name}={getattr(cfg, name)} must be at least 1, or null (intrinsic_history: the whole run; "
                "final_eval_episodes: eval_episodes)")
    if cfg.intrinsic_history is not None and cfg.intrinsic_history_values > 100_000_000:
        bad(f"intrinsic_history={cfg.intrinsic_history} gradient steps is {cfg.intrinsic_history_values:,} raw "
            "values (> 100M) for the window's ring buffer: pick a shorter window, or null to count the whole run "
            "without a ring")
    if (cfg.use_intrinsic_models and cfg.intrinsic_history is None
            and cfg.total_steps * cfg.intrinsic_values_per_step >= 2**31):
        bad(f"total_steps={cfg.total_steps} x {cfg.intrinsic_values_per_step} raw values per step overflows the "
            "normaliser's whole-run counts (2^31): set a window, e.g. --set intrinsic_history=400000")
    for name in ("learning_starts", "eval_every", "her_k", "video_every"):
        if getattr(cfg, name) < 0:
            bad(f"{name}={getattr(cfg, name)} must be non-negative")
    if (not cfg.hidden_sizes or not cfg.intrinsic_hidden_sizes
            or min(cfg.hidden_sizes + cfg.intrinsic_hidden_sizes) < 1):
        bad("hidden_sizes and intrinsic_hidden_sizes need at least one layer of positive width, e.g. [256, 256, 256]")
    for name in ("learning_rate", "intrinsic_lr", "ent_coef_init", "action_scale"):
        if not getattr(cfg, name) > 0:
            bad(f"{name}={getattr(cfg, name)} must be positive")
    if not (0 < cfg.tau <= 1 and 0 <= cfg.gamma < 1):
        bad(f"tau={cfg.tau}, gamma={cfg.gamma}: need 0 < tau <= 1 and 0 <= gamma < 1")
