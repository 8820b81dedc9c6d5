"""Names of what one gradient step reports (means over a log interval). No JAX: the run directory's readers and
writers use these names too (`mcrl.run.rundir.metric_columns`)."""
from __future__ import annotations

# Every run sums and logs these, in this order, whatever its reward: metrics.csv lays its columns out by them, and
# committed runs and a resumed run's header are compared byte for byte, so the built-in rewards' own names stay
# here (MC's model losses and raw KL, the others' `intrinsic_loss` and `mean_raw_intrinsic`: their
# `mcrl.algo.intrinsic.About.metrics`). A reward naming others gets them after these (`update_metrics`).
UPDATE_METRICS = ("actor_loss", "critic_loss", "ent_coef", "ent_coef_loss", "q_mean", "transition_model_loss",
                  "action_model_loss", "mean_ext_reward", "mean_intrinsic_reward", "mean_total_reward",
                  "mean_raw_kl", "intrinsic_loss", "mean_raw_intrinsic", "saturated_share", "logp_gap")
# Reported only by runs with intrinsic models: the normalised reward by all of them, the others by the rewards that
# name them (`About.metrics`: MC its models' losses and raw KL, RND, ICM and Disagreement `intrinsic_loss` and
# `mean_raw_intrinsic`), as are the names a reward adds (`update_metrics`).
INTRINSIC_METRICS = ("transition_model_loss", "action_model_loss", "mean_intrinsic_reward", "mean_raw_kl",
                     "intrinsic_loss", "mean_raw_intrinsic")
# The normaliser's bounds at the end of a log interval (raw-value percentiles), beside the means.
BOUNDS = ("intrinsic_bound_low", "intrinsic_bound_high")


def update_metrics(own: tuple[str, ...] = ()) -> tuple[str, ...]:
    """What a run whose reward reports `own` (its `About.metrics`) sums between log rows: `UPDATE_METRICS`, then
    those of `own` it lacks (none for a built-in reward)."""
    return (*UPDATE_METRICS, *(k for k in own if k not in UPDATE_METRICS))


def reported(own: tuple[str, ...] | None) -> tuple[str, ...]:
    """The metrics of a run whose intrinsic reward reports `own` (its `About.metrics`); None for plain SAC, which
    reports none of the intrinsic ones (a name a reward adds is one: `update_metrics`)."""
    mine = () if own is None else (*own, "mean_intrinsic_reward")
    sac = tuple(k for k in UPDATE_METRICS if k not in INTRINSIC_METRICS)
    return tuple(k for k in update_metrics(own or ()) if k in mine or k in sac)
