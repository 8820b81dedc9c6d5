"""Every intrinsic reward behind one interface, `IntrinsicReward`, and the one registry of them (config key
`intrinsic`; docs/intrinsic.md).

An intrinsic reward is a frozen dataclass built from the run's config (`from_config`) with three pure functions of
arrays, which `mcrl.algo.sac.Agent.update` calls inside the one jitted gradient step:

    reward.init(key) -> (params, untrained)
        `params` are trained by Adam (`intrinsic_lr`, one step per gradient step); `untrained` is what no gradient
        trains (RND's random target network, the running state statistics of RND and Disagreement; {} for MC, ICM).
    reward.step(params, untrained, s, a, s_next, key) -> Raw
        on a replay batch: the raw reward of every transition, the gradients of the models' loss, `untrained` after
        this batch, the metrics it reports (`metrics` names them) and the values its batch adds to the
        normaliser's history. The reward is computed with the parameters before their update.
    reward.reward(params, untrained, s, a, s_next) -> (B,)
        the raw reward of each transition alone, nothing updated (unseen transitions, a video's timeline).

All of them see the same inputs: the intrinsic state (`intrinsic_state`: the observation part by default) of the
sampled batch after HER relabelling, its action and next state. Their raw values go through the same percentile
normaliser into [intrinsic_reward_low, intrinsic_reward_high] and are mixed with weight intrinsic_alpha. `key` is
the reward's own (Disagreement's sample masks), so SAC's keys are the same with or without intrinsic models.

Adding a reward: a module with the class, and one line in `_REGISTRY` (or `register(name, cls)` at run time). A
reward in a package of its own declares it in the entry-point group `mcrl.intrinsic` (``mine = mine_pkg:Mine``):
`register` lasts one process, and `mcrl eval`, `render`, `--resume` and a sweep's workers are other processes, so
an installed package's declaration is how they find it again. This module imports no JAX, so the config
validates `intrinsic` against the registry (`known`) cheaply; a reward's module is imported when it is first
built (`get`).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable

from mcrl.errors import MCRLError

__all__ = ["ENTRY_POINTS", "GENERIC_METRICS", "IntrinsicReward", "Raw", "Sizes", "get", "known", "names",
           "register"]

# the entry-point group in which an installed package declares its rewards: name = "module:attribute"
ENTRY_POINTS = "mcrl.intrinsic"
# what a reward reports unless it names its own (`IntrinsicReward.metrics`): columns of metrics.csv
GENERIC_METRICS = ("intrinsic_loss", "mean_raw_intrinsic")


class Raw(NamedTuple):
    """One batch through an intrinsic reward's models (before the percentile normaliser)."""

    raw: Any  # (B,) raw reward of each transition
    grads: Any  # of the models' loss with respect to the trained parameters
    untrained: Any  # the part no gradient trains, after this batch
    metrics: dict  # the reward's own metrics of this batch, by name (its `metrics`)
    history: Any = None  # the values this batch adds to the normaliser's history; None: `raw`


@runtime_checkable
class IntrinsicReward(Protocol):
    """What `mcrl.algo.sac.Agent` needs of an intrinsic reward (see the module's docstring)."""

    metrics: ClassVar[tuple[str, ...]]  # the metrics.csv columns `step` fills (mcrl.algo.metrics.UPDATE_METRICS)
    title: ClassVar[str]  # its name in a video's timeline, e.g. "MC", "RND"
    raw_label: ClassVar[str]  # its raw value's row in a video's timeline, e.g. "raw KL (nats)"

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int) -> "IntrinsicReward": ...

    def init(self, key) -> tuple[Any, Any]: ...

    def step(self, params, untrained, s, a, s_next, key) -> Raw: ...

    def reward(self, params, untrained, s, a, s_next) -> Any: ...


@dataclass(frozen=True)
class Sizes:
    """The sizes most rewards are built from: the intrinsic state's and action's dimensions, the width of every
    hidden layer (the widest of `intrinsic_hidden_sizes`; each paper's own depth), initialisation and matmul
    precision. A base class: it supplies `from_config` and the generic metrics."""

    state_dim: int
    action_dim: int
    width: int = 256
    init_scheme: str = "torch"
    matmul_precision: str = "float32"

    metrics: ClassVar[tuple[str, ...]] = GENERIC_METRICS
    title: ClassVar[str] = "intrinsic"
    raw_label: ClassVar[str] = "raw intrinsic reward"

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
