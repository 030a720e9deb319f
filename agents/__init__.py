"""Calibration-scheduling policies implementing :class:`uwb_env.env.CalibrationPolicy`."""

from uwb_env.agents.baselines import (
    AlwaysPolicy,
    FixedIntervalPolicy,
    NeverPolicy,
    OraclePolicy,
    RandomPolicy,
    ResidualTriggerPolicy,
    UncertaintyThresholdPolicy,
)

__all__ = [
    "AlwaysPolicy",
    "FixedIntervalPolicy",
    "NeverPolicy",
    "OraclePolicy",
    "RandomPolicy",
    "ResidualTriggerPolicy",
    "UncertaintyThresholdPolicy",
]
