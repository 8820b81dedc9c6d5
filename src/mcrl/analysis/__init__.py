"""Reading experiments and runs: statistics, plots, and the `mcrl report`."""
