"""Names of what one gradient step reports (means over a log interval). No JAX: the run directory's readers and
writers use these names too (`mcrl.run.rundir.METRIC_COLUMNS`)."""
from __future__ import annotations

UPDATE_METRICS = ("actor_loss", "critic_loss", "ent_coef", "ent_coef_loss", "q_mean", "transition_model_loss",
                  "action_model_loss", "mean_ext_reward", "mean_intrinsic_reward", "mean_total_reward",
                  "mean_raw_kl", "intrinsic_loss", "mean_raw_intrinsic", "saturated_share", "logp_gap")
# Reported only by runs with intrinsic models: the normalised reward by all of them, the others by the rewards that
# name them (`mcrl.algo.intrinsic.IntrinsicReward.metrics`: MC its models' losses and raw KL, RND, ICM and
# Disagreement `intrinsic_loss` and `mean_raw_intrinsic`).
INTRINSIC_METRICS = ("transition_model_loss", "action_model_loss", "mean_intrinsic_reward", "mean_raw_kl",
                     "intrinsic_loss", "mean_raw_intrinsic")
# The normaliser's bounds at the end of a log interval (raw-value percentiles), beside the means.
BOUNDS = ("intrinsic_bound_low", "intrinsic_bound_high")


def reported(own: tuple[str, ...] | None) -> tuple[str, ...]:
    """The metrics of a run whose intrinsic reward reports `own` (its `metrics`); None for plain SAC, which reports
    none of the intrinsic ones."""
    mine = () if own is None else (*own, "mean_intrinsic_reward")
    return tuple(k for k in UPDATE_METRICS if k in mine or k not in INTRINSIC_METRICS)
