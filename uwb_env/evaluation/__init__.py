"""Statistics for comparing schedulers over seeds (free of RL APIs); see :mod:`.stats`."""

from uwb_env.evaluation.stats import (
    CATASTROPHIC_M,
    Estimate,
    catastrophic_rate,
    iqm,
    matched_budget,
    paired_difference,
    probability_of_improvement,
    summarize_errors,
)

__all__ = ["CATASTROPHIC_M", "Estimate", "catastrophic_rate", "iqm", "matched_budget", "paired_difference",
           "probability_of_improvement", "summarize_errors"]
