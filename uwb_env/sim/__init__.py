"""Simulator core: world, motion, odometry, UWB ranging, calibration-round timing.

This package must not import gymnasium or pettingzoo (the env classes are thin adapters).
"""

from uwb_env.sim.calibration_round import CalibrationRound, RoundTiming
from uwb_env.sim.motion import MotionModel
from uwb_env.sim.odometry import OdometryModel
from uwb_env.sim.ranging import RangeFit, RangeModel, fit_range_data, load_range_data
from uwb_env.sim.world import World

__all__ = [
    "CalibrationRound",
    "MotionModel",
    "OdometryModel",
    "RangeFit",
    "RangeModel",
    "RoundTiming",
    "World",
    "fit_range_data",
    "load_range_data",
]
