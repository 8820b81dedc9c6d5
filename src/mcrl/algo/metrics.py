"""Names of what one SAC-MC gradient step reports (means over a log interval). No JAX: the run directory's
readers and writers use these names too (`mcrl.run.rundir.METRIC_COLUMNS`)."""

UPDATE_METRICS = ("actor_loss", "critic_loss", "ent_coef", "ent_coef_loss", "q_mean", "transition_model_loss",
                  "action_model_loss", "mean_ext_reward", "mean_mc_reward", "mean_total_reward", "mean_raw_kl")
MC_METRICS = ("transition_model_loss", "action_model_loss", "mean_mc_reward", "mean_raw_kl")  # only with MC models
