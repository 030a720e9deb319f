"""The environment in PettingZoo's module convention: ``env`` (AEC), ``raw_env``, ``parallel_env``.

    from uwb_env import uwb_calibration_v0
    env = uwb_calibration_v0.parallel_env()   # ParallelEnv (the native API)
    aec = uwb_calibration_v0.env()            # AEC, with PettingZoo's standard wrappers

Spaces, reward, termination and arguments: see :mod:`uwb_env.env.parallel_env`.
"""

from __future__ import annotations

from pettingzoo.utils import parallel_to_aec, wrappers

from uwb_env.env.parallel_env import UWBCalibrationParallelEnv


def parallel_env(**kwargs) -> UWBCalibrationParallelEnv:
    return UWBCalibrationParallelEnv(**kwargs)


def raw_env(**kwargs):
    """The AEC view of the parallel env, unwrapped."""
    return parallel_to_aec(parallel_env(**kwargs))


def env(**kwargs):
    """The AEC env with PettingZoo's usual wrappers (out-of-bounds actions and order checks)."""
    aec = raw_env(**kwargs)
    aec = wrappers.AssertOutOfBoundsWrapper(aec)
    return wrappers.OrderEnforcingWrapper(aec)
