"""Every intrinsic reward behind one interface, `IntrinsicReward`, and the one registry of them (config key
`intrinsic`; docs/intrinsic.md).

An intrinsic reward is a frozen dataclass built from the run's config (`from_config`) with three pure functions of
arrays, which `mcrl.algo.sac.Agent.update` calls inside the one jitted gradient step:

    reward.init(key) -> (params, untrained)
        `params` are trained by Adam (`intrinsic_lr`, one step per gradient step); `untrained` is what no gradient
        trains (RND's random target network, the running state statistics of RND and Disagreement; {} for MC, ICM).
    reward.step(params, untrained, s, a, s_next, key) -> Raw
        on a replay batch: the raw reward of every transition, the gradients of the models' loss, `untrained` after
        this batch, the metrics it reports (`about.metrics` names them) and the values its batch adds to the
        normaliser's history. The reward is computed with the parameters before their update.
    reward.reward(params, untrained, s, a, s_next) -> (B,)
        the raw reward of each transition alone, nothing updated (unseen transitions, a video's timeline).

All of them see the same inputs: the intrinsic state (`intrinsic_state`: the observation part by default) of the
sampled batch after HER relabelling, its action and next state. Their raw values go through the same percentile
normaliser into [intrinsic_reward_low, intrinsic_reward_high] and are mixed with weight intrinsic_alpha. `key` is
the reward's own (Disagreement's sample masks), so SAC's keys are the same with or without intrinsic models.

What the rest of mcrl knows of a reward without building it is its `About` (`about(name)`): its title (a video's
rows, the report's panels), the name of an arm that mixes it in ("SAC-MC 0.2", "SAC+RND 0.2"), its metrics.csv
columns and which of them holds its raw value's batch mean, the config keys only it reads, and how many values one
gradient step adds to the normaliser's history. MC's is one like the others'.

Adding a reward: a module with the class (its `about` included), and one line in `_REGISTRY` (or
`register(name, cls)` at run time). A reward in a package of its own declares it in the entry-point group
`mcrl.intrinsic` (``mine = mine_pkg:Mine``): `register` lasts one process, and `mcrl eval`, `render`, `--resume`
and a sweep's workers are other processes, so an installed package's declaration is how they find it again. This
module imports no JAX, so the config validates `intrinsic` against the registry (`known`) and reads the built-in
rewards' `About` (`ABOUT`) cheaply; a reward's module is imported when it is first built (`get`), or when the
`About` of a reward not built in is first asked for.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, NamedTuple, Protocol, runtime_checkable

from mcrl.errors import MCRLError

__all__ = ["ABOUT", "ENTRY_POINTS", "GENERIC_METRICS", "THESIS_REWARD", "About", "IntrinsicReward", "Raw", "Sizes",
           "about", "get", "known", "names", "owned_keys", "register"]

# the entry-point group in which an installed package declares its rewards: name = "module:attribute"
ENTRY_POINTS = "mcrl.intrinsic"
# what a reward reports unless it names its own (`About.metrics`): columns of metrics.csv
GENERIC_METRICS = ("intrinsic_loss", "mean_raw_intrinsic")
# the thesis' reward: the config's default `intrinsic`, and what the report means by "SAC-MC" (the thesis' arms)
THESIS_REWARD = "mc"


def _batch_values(cfg) -> int:
    """Every transition of a batch adds its raw value to the normaliser's history: `batch_size` a step."""
    return cfg.batch_size


@dataclass(frozen=True)
class About:
    """What mcrl knows of a reward without building it (no JAX): the config, the run's files, the report and the
    video read this, never the reward's name. A reward's class holds it as `about`."""

    title: str  # its name in a video's timeline and the report's panels: "MC", "RND"
    algorithm: str  # an arm that mixes it in, before the weight: "SAC-MC" ("SAC-MC 0.2"), "SAC+RND"
    metrics: tuple[str, ...] = GENERIC_METRICS  # the metrics.csv columns its `step` fills (its `Raw.metrics`)
    raw_metric: str = "mean_raw_intrinsic"  # the one of `metrics` holding its raw value's batch mean
    raw_label: str = "raw intrinsic reward"  # its raw value, with its unit: a video's row, a report panel
    own_keys: tuple[str, ...] = ()  # config keys only it reads: refused at a value other than their default
    # for another reward (`mcrl.config.validate`)
    values_per_step: Callable[[Any], int] = _batch_values  # cfg -> raw values one gradient step adds to the
    # normaliser's history (`Raw.history`; `Config.intrinsic_values_per_step`)

    @classmethod
    def generic(cls, name: str) -> "About":
        """What a report or video says of a reward that names no `about`, or of one no longer installed (a
        foreign or old run's `intrinsic`): its name, the generic metrics."""
        return cls(name, f"SAC+{name}")


class Raw(NamedTuple):
    """One batch through an intrinsic reward's models (before the percentile normaliser)."""

    raw: Any  # (B,) raw reward of each transition
    grads: Any  # of the models' loss with respect to the trained parameters
    untrained: Any  # the part no gradient trains, after this batch
    metrics: dict  # the reward's own metrics of this batch, by name (its `about.metrics`)
    history: Any = None  # the values this batch adds to the normaliser's history; None: `raw`


@runtime_checkable
class IntrinsicReward(Protocol):
    """What `mcrl.algo.sac.Agent` needs of an intrinsic reward (see the module's docstring)."""

    about: ClassVar[About]  # its title, metrics.csv columns, raw value's column and label, own config keys

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int) -> "IntrinsicReward": ...

    def init(self, key) -> tuple[Any, Any]: ...

    def step(self, params, untrained, s, a, s_next, key) -> Raw: ...

    def reward(self, params, untrained, s, a, s_next) -> Any: ...


@dataclass(frozen=True)
class Sizes:
    """The sizes most rewards are built from: the intrinsic state's and action's dimensions, the width of every
    hidden layer (the widest of `intrinsic_hidden_sizes`; each paper's own depth), initialisation and matmul
    precision. A base class: it supplies `from_config` and the generic metrics (a subclass gives its `about`)."""

    state_dim: int
    action_dim: int
    width: int = 256
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int):
        return cls(state_dim, action_dim, max(cfg.intrinsic_hidden_sizes), cfg.init, cfg.matmul_precision)

    @staticmethod
    def generic_metrics(loss, raw) -> dict:
        """`GENERIC_METRICS` of a batch: what the models minimise, and the raw reward's batch mean."""
        return {"intrinsic_loss": loss, "mean_raw_intrinsic": raw.mean()}


# `intrinsic` -> its class, as "module:attribute" (imported on first use) or the class itself
_REGISTRY: dict[str, Any] = {
    "mc": "mcrl.algo.mc:MC",  # the thesis' morphological computation
    "rnd": "mcrl.algo.rnd:RND",
    "icm": "mcrl.algo.icm:ICM",
    "disagreement": "mcrl.algo.disagreement:Disagreement",
}


def _mc_values_per_step(cfg) -> int:
    """MC's batch variant (`mc_reduction=batch`, the thesis' code) adds one batch-mean KL a step."""
    return 1 if cfg.mc_reduction == "batch" else cfg.batch_size


_BUILT_IN = dict(_REGISTRY)  # what the names of `ABOUT` are registered as, unless registered again


# The built-in rewards' `About`, beside the registry so that the config and the report know them without importing
# a reward's models; each class points at its entry (`about = ABOUT["mc"]`).
ABOUT: dict[str, About] = {
    "mc": About("MC", "SAC-MC", ("transition_model_loss", "action_model_loss", "mean_raw_kl"), "mean_raw_kl",
                "raw KL (nats)", ("mc_reduction",), _mc_values_per_step),
    "rnd": About("RND", "SAC+RND", raw_label="raw RND error"),
    "icm": About("ICM", "SAC+ICM", raw_label="raw ICM error"),
    "disagreement": About("Disagreement", "SAC+Disagreement", raw_label="raw disagreement"),
}


def register(name: str, reward: Any) -> None:
    """Make `reward` (a class implementing `IntrinsicReward`, or "module:attribute" naming one) the value
    `intrinsic=name` selects, in this process (an installed package declares it for every process: `ENTRY_POINTS`)."""
    _REGISTRY[name] = reward


def _discover() -> None:
    """Add the rewards installed packages declare (`ENTRY_POINTS`) as "module:attribute", imported on first use;
    a name registered here keeps its entry."""
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINTS):
        _REGISTRY.setdefault(ep.name, ep.value)


def known(name: str) -> bool:
    """Whether `intrinsic=name` selects a reward: registered, or declared by an installed package. The installed
    packages are read only for a name not registered, so the built-in rewards cost no metadata scan."""
    if name not in _REGISTRY:
        _discover()
    return name in _REGISTRY


def names() -> tuple[str, ...]:
    """The values `intrinsic` may take, those installed packages declare included."""
    _discover()
    return tuple(_REGISTRY)


def get(name: str) -> type:
    """The class registered as `name` (KeyError for an unknown name); MCRLError when its module cannot be
    imported."""
    if not known(name):
        raise KeyError(name)
    entry = _REGISTRY[name]
    if isinstance(entry, str):
        module, _, attr = entry.partition(":")
        try:
            entry = importlib.import_module(module)
            for part in attr.split("."):  # an entry point's attribute may be dotted (module:Outer.Inner)
                entry = getattr(entry, part)
        except (ImportError, AttributeError) as e:
            raise MCRLError(f"intrinsic reward {name!r} ({_REGISTRY[name]}) cannot be loaded: {type(e).__name__}: "
                            f"{e}; reinstall the package that declares it (entry-point group {ENTRY_POINTS})") from None
        _REGISTRY[name] = entry
    return entry


def about(name: str) -> About:
    """What mcrl knows of reward `name` (`About`): a built-in's from `ABOUT` (nothing imported), another's from its
    class's `about` (its module imported). A class without one, a name no longer registered or a package no
    longer installed (an old or foreign run's config in a report) get `About.generic(name)`, not an error."""
    if not known(name):
        return About.generic(name)
    if name in ABOUT and _REGISTRY[name] == _BUILT_IN[name]:  # a built-in not imported yet
        return ABOUT[name]
    try:
        cls = get(name)
    except MCRLError:
        return About.generic(name)
    return getattr(cls, "about", None) or About.generic(name)


def owned_keys() -> dict[str, str]:
    """Config keys only one reward reads (`About.own_keys`) -> that reward's name: the built-ins' and those of
    rewards registered here as classes (a declared reward not imported yet is not imported for this: the config
    validates without JAX)."""
    abouts = {**ABOUT, **{n: e.about for n, e in _REGISTRY.items() if not isinstance(e, str) and hasattr(e, "about")}}
    return {key: name for name, a in abouts.items() for key in a.own_keys}
