"""Closed-loop steered rollouts in the LIBERO simulator: episodes, their records, statistics, plots and reports."""
