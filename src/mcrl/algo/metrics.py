"""Names of what one SAC-MC gradient step reports (means over a log interval). No JAX: the run directory's
readers and writers use these names too (`mcrl.run.rundir.METRIC_COLUMNS`)."""
from __future__ import annotations

UPDATE_METRICS = ("actor_loss", "critic_loss", "ent_coef", "ent_coef_loss", "q_mean", "transition_model_loss",
                  "action_model_loss", "mean_ext_reward", "mean_mc_reward", "mean_total_reward", "mean_raw_kl",
                  "intrinsic_loss", "mean_raw_intrinsic", "saturated_share", "logp_gap")
MC_METRICS = ("transition_model_loss", "action_model_loss", "mean_mc_reward", "mean_raw_kl")  # only with MC models
# only with RND, ICM or Disagreement models; `mean_mc_reward` (the normalised intrinsic reward) is theirs too
INTRINSIC_METRICS = ("intrinsic_loss", "mean_raw_intrinsic", "mean_mc_reward")


def reported(intrinsic_models: str | None) -> tuple[str, ...]:
    """The metrics a run reports whose intrinsic models are `intrinsic_models` (`Config.intrinsic_models`: None
    for plain SAC, which reports none of the intrinsic ones)."""
    own = () if intrinsic_models is None else MC_METRICS if intrinsic_models == "mc" else INTRINSIC_METRICS
    return tuple(k for k in UPDATE_METRICS if k in own or (k not in MC_METRICS and k not in INTRINSIC_METRICS))
