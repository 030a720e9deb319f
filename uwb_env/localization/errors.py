"""Typed errors of the localization backend (never silent NaN)."""


class LocalizationError(ValueError):
    """Base class: the input cannot give a meaningful solution."""


class TooFewAnchorsError(LocalizationError):
    """Fewer anchors than the frame needs (3 in 2D, 4 in 3D)."""


class InvalidRangeError(LocalizationError):
    """A range is non-finite where it must be finite, or negative."""


class DisconnectedGraphError(LocalizationError):
    """The inter-anchor range graph splits into components that cannot be related."""


class GeometryError(LocalizationError):
    """Degenerate geometry: coincident or collinear (coplanar in 3D) anchors, frame unfixable."""


class SolverArgumentError(ValueError):
    """A solver argument is out of its domain (the message names the argument and its value)."""
