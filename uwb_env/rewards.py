"""The reward, defined once for the single env (``LocalizationSystem.reward_terms``) and the
batched one (``BatchedSystem.rewards``): a weighted sum of the step's mean tag error, mean
anchor error (capped), the share of the step the channel spent calibrating, and a cost per
round started. Each term is returned separately (the single env's ``infos`` report them)."""

from __future__ import annotations

REWARD_TERMS = ("tag_error", "anchor_error", "calibration_time", "calibration_start")


def reward_terms(config, tag_error_m, anchor_error_m, calibrating_fraction, round_started) -> dict:
    """The reward's terms from ``config`` (an ``EnvConfig``'s weights): floats for one env, or
    (B,) arrays for a batch (``round_started`` bool). The reward is their sum."""
    return dict(zip(REWARD_TERMS, (
        -config.tag_error_weight * tag_error_m,
        -config.anchor_error_weight * anchor_error_m,
        -config.calibration_time_weight * calibrating_fraction,
        -config.calibration_start_cost * round_started,
    ), strict=True))
