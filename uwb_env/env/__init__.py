"""RL adapters over :class:`uwb_env.system.LocalizationSystem`."""

from uwb_env.env.parallel_env import UWBCalibrationParallelEnv
from uwb_env.env.policy import CalibrationPolicy, RolloutResult, rollout
from uwb_env.env.scheduler_env import CalibrationSchedulingEnv

__all__ = ["CalibrationPolicy", "CalibrationSchedulingEnv", "RolloutResult", "UWBCalibrationParallelEnv", "rollout"]
