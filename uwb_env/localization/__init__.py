"""Localization backend: anchor autocalibration, tag multilateration, bounds, alignment.

No RL imports; used by the environments and by the hardware mode alike.
"""

from uwb_env.localization.alignment import aligned_errors, paper_frame, rigid_align
from uwb_env.localization.bounds import anchor_fisher_information, crlb_anchors, crlb_tags
from uwb_env.localization.calibration import CalibrationResult, calibrate_anchors, classical_mds
from uwb_env.localization.errors import (
    DisconnectedGraphError,
    GeometryError,
    InvalidRangeError,
    LocalizationError,
    TooFewAnchorsError,
)
from uwb_env.localization.models import PairRangeModel, TagRangeModel
from uwb_env.localization.multilateration import TagFixResult, locate_tags
from uwb_env.localization.relocation import RelocationResult, relocate_anchor

__all__ = [
    "CalibrationResult",
    "DisconnectedGraphError",
    "GeometryError",
    "InvalidRangeError",
    "LocalizationError",
    "PairRangeModel",
    "RelocationResult",
    "TagFixResult",
    "TagRangeModel",
    "TooFewAnchorsError",
    "aligned_errors",
    "anchor_fisher_information",
    "calibrate_anchors",
    "classical_mds",
    "crlb_anchors",
    "crlb_tags",
    "locate_tags",
    "paper_frame",
    "relocate_anchor",
    "rigid_align",
]
