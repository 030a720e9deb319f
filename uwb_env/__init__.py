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

__all__ = [
    "CalibrationConfig",
    "ConfigError",
    "MotionConfig",
    "OdometryConfig",
    "RangingConfig",
    "SimConfig",
    "__version__",
]
