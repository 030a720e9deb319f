"""uwb-env: mobile UWB localization with periodic anchor autocalibration."""

from uwb_env.config import (
    CalibrationConfig,
    ConfigError,
    MotionConfig,
    OdometryConfig,
    RangingConfig,
    SimConfig,
)

__version__ = "0.1.0"


def parallel_env(**kwargs):
    """The PettingZoo ParallelEnv (PettingZoo's factory convention); see its docstring."""
    from uwb_env.env.parallel_env import UWBCalibrationParallelEnv

    return UWBCalibrationParallelEnv(**kwargs)


def _register() -> None:
    import gymnasium

    if "uwb_env/CalibrationScheduling-v0" not in gymnasium.registry:
        gymnasium.register(
            id="uwb_env/CalibrationScheduling-v0",
            entry_point="uwb_env.env.scheduler_env:CalibrationSchedulingEnv",
            vector_entry_point="uwb_env.env.vector_env:CalibrationSchedulingVectorEnv",
        )


_register()

__all__ = [
    "CalibrationConfig",
    "ConfigError",
    "MotionConfig",
    "OdometryConfig",
    "RangingConfig",
    "SimConfig",
    "__version__",
    "parallel_env",
]
