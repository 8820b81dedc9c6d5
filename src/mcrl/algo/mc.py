"""Morphological computation (MC): the two next-state models and the KL between them.

MC of a transition is KL( p(s'|s,a) || p(s'|a) ): how much the current state (the body) tells about
the next state beyond what the action alone tells. Both models are diagonal Gaussians, so the KL is
closed-form. The same forward pass gives the models' NLL loss and the KL, so the agent pays for it once.

`MC` is the thesis' intrinsic reward behind the interface every intrinsic reward shares
(`mcrl.algo.intrinsic.IntrinsicReward`), with its two reductions (`mc_reduction`): each transition its own KL
(the thesis' text) or one batch-mean KL for the whole batch (the thesis' code). `measure` fits the same models to
logged transitions offline (`mcrl measure`). Everything here is a pure function of arrays, except
`load_transitions`, which reads and checks `measure`'s data file.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from mcrl.algo.intrinsic import ABOUT, About, Raw
from mcrl.algo.networks import ActionModel, TransitionModel
from mcrl.errors import MCRLError

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def gaussian_kl(mu_p, log_std_p, mu_q, log_std_q):
    """Elementwise KL( N(mu_p, std_p) || N(mu_q, std_q) ) in nats."""
    var_ratio = jnp.exp(2.0 * (log_std_p - log_std_q))
    mean_term = jnp.square((mu_p - mu_q) * jnp.exp(-log_std_q))
    return (log_std_q - log_std_p) + 0.5 * (var_ratio + mean_term - 1.0)


def gaussian_nll(x, mu, log_std):
    """Elementwise negative log-likelihood of x under N(mu, exp(log_std))."""
    return log_std + 0.5 * jnp.square((x - mu) * jnp.exp(-log_std)) + _HALF_LOG_2PI


class MCOutputs(NamedTuple):
    mu_t: jax.Array  # transition model p(s'|s,a)
    log_std_t: jax.Array
    mu_a: jax.Array  # action-only model p(s'|a)
    log_std_a: jax.Array


@dataclass(frozen=True)
class MCModels:
    """The pair of next-state models; `params` is {"transition": ..., "action": ...}."""

    state_dim: int
    hidden: tuple[int, ...]
    init_scheme: str = "torch"  # see mcrl.algo.networks
    matmul_precision: str = "float32"  # float32 | bfloat16, see mcrl.algo.networks

    @property
    def transition(self) -> TransitionModel:
        return TransitionModel(self.hidden, self.state_dim, self.init_scheme, self.matmul_precision)

    @property
    def action(self) -> ActionModel:
        return ActionModel(self.hidden, self.state_dim, self.init_scheme, self.matmul_precision)

    def init(self, key, action_dim: int):
        kt, ka = jax.random.split(key)
        s = jnp.zeros((1, self.state_dim))
        a = jnp.zeros((1, action_dim))
        return {"transition": self.transition.init(kt, s, a)["params"],
                "action": self.action.init(ka, a)["params"]}

    def forward(self, params, s, a) -> MCOutputs:
        mu_t, ls_t = self.transition.apply({"params": params["transition"]}, s, a)
        mu_a, ls_a = self.action.apply({"params": params["action"]}, a)
        return MCOutputs(mu_t, ls_t, mu_a, ls_a)

    def loss(self, params, s, a, s_next):
        """NLL of the observed next state under each model (mean over batch and dimensions).

        Returns (total loss, (outputs, transition loss, action loss)); the outputs feed `transition_kl`,
        so the reward and the loss share one forward pass.
        """
        out = self.forward(params, s, a)
        lt = gaussian_nll(s_next, out.mu_t, out.log_std_t).mean()
        la = gaussian_nll(s_next, out.mu_a, out.log_std_a).mean()
        return lt + la, (out, lt, la)


def transition_kl(out: MCOutputs) -> jax.Array:
    """Per-transition MC: KL(transition || action-only) summed over state dimensions, shape (batch,)."""
    kl = gaussian_kl(out.mu_t, out.log_std_t, out.mu_a, out.log_std_a).sum(-1)
    # A diverging model must not poison the reward with NaN/inf; KL is >= 0 analytically.
    return jnp.nan_to_num(jnp.maximum(kl, 0.0), nan=0.0, posinf=jnp.finfo(kl.dtype).max)


@dataclass(frozen=True)
class MC:
    """MC as an intrinsic reward (`intrinsic=mc`): the raw reward of a transition is its KL in nats; the models
    train on both NLLs; params {"transition", "action"}, nothing untrained. With `reduction="batch"` (the thesis'
    code) every transition of a batch gets the batch-mean KL, and the batch adds that one value to the history."""

    state_dim: int
    action_dim: int
    hidden: tuple[int, ...] = (256,) * 5
    init_scheme: str = "torch"
    matmul_precision: str = "float32"
    reduction: str = "transition"  # transition (thesis text) | batch (thesis code)

    about: ClassVar[About] = ABOUT["mc"]  # its models' losses and raw KL; `mc_reduction` its own key

    @classmethod
    def from_config(cls, cfg, state_dim: int, action_dim: int) -> "MC":
        return cls(state_dim, action_dim, tuple(cfg.intrinsic_hidden_sizes), cfg.init, cfg.matmul_precision,
                   cfg.mc_reduction)

    @property
    def models(self) -> MCModels:
        return MCModels(self.state_dim, self.hidden, self.init_scheme, self.matmul_precision)

    def init(self, key):
        return self.models.init(key, self.action_dim), {}

    def step(self, params, untrained, s, a, s_next, key=None) -> Raw:
        # one forward pass gives both models' loss and the KL
        (_, (out, lt, la)), grads = jax.value_and_grad(self.models.loss, has_aux=True)(params, s, a, s_next)
        kl = history = transition_kl(out)
        if self.reduction == "batch":  # the thesis' code: one batch-mean value for every transition
            kl = jnp.broadcast_to(kl.mean(), kl.shape)
            history = kl[:1]  # one history value per step, as its code
        return Raw(kl, grads, untrained,
                   {"transition_model_loss": lt, "action_model_loss": la, "mean_raw_kl": kl.mean()}, history)

    def reward(self, params, untrained, s, a, s_next):
        """Each transition's own KL (the predictions need no s')."""
        return transition_kl(self.models.forward(params, s, a))


# --------------------------------------------------------------------------------------------
# MC as a measurement: fit both models to logged transitions and report the mean KL (`mcrl measure`).
# --------------------------------------------------------------------------------------------

def load_transitions(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(states, actions, next_states) of a `measure` data file: an .npz with those three 2-d arrays, checked."""
    p = Path(path)
    if not p.is_file():
        raise MCRLError(f"data file {path} not found: give an .npz with arrays states, actions, next_states")
    try:
        with np.load(p, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as e:  # a corrupt or non-npz file
        raise MCRLError(f"cannot read {path} as .npz ({type(e).__name__}): save it with numpy.savez") from None
    missing = [k for k in ("states", "actions", "next_states") if k not in arrays]
    if missing:
        raise MCRLError(f"{path} lacks array(s) {missing}: it needs states (N, ds), actions (N, da), "
                        "next_states (N, ds)")
    s, a, s2 = (np.asarray(arrays[k]) for k in ("states", "actions", "next_states"))
    if s.ndim != 2 or a.ndim != 2 or s2.ndim != 2:
        raise MCRLError(f"{path}: states {s.shape}, actions {a.shape}, next_states {s2.shape} must all be 2-d "
                        "(N, dim); reshape them")
    if not (len(s) == len(a) == len(s2)) or s.shape[1] != s2.shape[1]:
        raise MCRLError(f"{path}: states {s.shape}, actions {a.shape}, next_states {s2.shape} disagree: need the "
                        "same N everywhere and next_states shaped like states")
    if len(s) < 10:
        raise MCRLError(f"{path} holds {len(s)} transitions: measuring MC needs at least 10 (thousands for accuracy)")
    if not all(np.isfinite(x).all() for x in (s, a, s2)):
        raise MCRLError(f"{path} contains NaN or inf values: clean the data first")
    return s, a, s2


@dataclass
class MeasureResult:
    mean_kl: float  # nats, mean over the held-out transitions (`heldout`), which no model was fitted on
    per_transition_kl: np.ndarray  # for every input transition, held out or fitted on
    steps: int  # gradient steps taken (best held-out NLL)
    heldout_nll: float
    heldout: np.ndarray | None = None  # the held-out transitions' indices, ascending


def measure(states: np.ndarray, actions: np.ndarray, next_states: np.ndarray, *, hidden=(256,) * 5,
            lr: float = 1e-3, batch_size: int = 256, max_steps: int = 20_000, eval_every: int = 500,
            patience: int = 6, heldout: float = 0.2, seed: int = 0, progress=None) -> MeasureResult:
    """Fit p(s'|s,a) and p(s'|a) by NLL and return the mean per-transition KL in nats.

    Inputs and targets are standardised (KL is invariant to per-dimension affine maps of s'), a held-out
    split stops training at the best held-out NLL (the transition model's variance overfits otherwise),
    and the KL is reported on the held-out transitions with the best parameters.
    """
    s, a, s2 = (np.asarray(x, np.float32) for x in (states, actions, next_states))
    n = len(s)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    n_val = max(1, int(n * heldout))
    val, tr = perm[:n_val], perm[n_val:]

    def stats(x):
        m, sd = x[tr].mean(0), x[tr].std(0)
        return m, np.where(sd > 1e-8, sd, 1.0)

    (ms, ss), (ma, sa), (m2, s2d) = stats(s), stats(a), stats(s2)
    s_n, a_n, s2_n = (s - ms) / ss, (a - ma) / sa, (s2 - m2) / s2d

    models = MCModels(state_dim=s.shape[1], hidden=tuple(hidden))
    params = models.init(jax.random.PRNGKey(seed), a.shape[1])
    opt = optax.adam(lr)
    opt_state = opt.init(params)

    @jax.jit
    def step(params, opt_state, idx):
        (loss, _), g = jax.value_and_grad(models.loss, has_aux=True)(params, s_n[idx], a_n[idx], s2_n[idx])
        upd, opt_state = opt.update(g, opt_state, params)
        return optax.apply_updates(params, upd), opt_state, loss

    @jax.jit
    def evaluate(params, s, a, s2):
        loss, (out, _, _) = models.loss(params, s, a, s2)
        return loss, transition_kl(out)

    s_n, a_n, s2_n = jnp.asarray(s_n), jnp.asarray(a_n), jnp.asarray(s2_n)
    best = (np.inf, params, 0)
    bad_evals = 0
    for t in range(1, max_steps + 1):
        idx = rng.choice(tr, size=min(batch_size, len(tr)), replace=False)
        params, opt_state, _ = step(params, opt_state, idx)
        if t % eval_every == 0 or t == max_steps:
            v_loss, _ = evaluate(params, s_n[val], a_n[val], s2_n[val])
            v_loss = float(v_loss)
            if progress is not None:
                progress(t, v_loss)
            if v_loss < best[0]:
                best, bad_evals = (v_loss, params, t), 0
            else:
                bad_evals += 1
                if bad_evals >= patience:
                    break
    v_loss, params, t_best = best
    _, kl_all = evaluate(params, s_n, a_n, s2_n)
    kl_all = np.asarray(kl_all, np.float64)
    return MeasureResult(mean_kl=float(kl_all[val].mean()), per_transition_kl=kl_all, steps=t_best,
                         heldout_nll=v_loss, heldout=np.sort(val))
