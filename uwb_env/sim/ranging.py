"""UWB two-way-ranging measurement model fitted to measured DWM1001 data.

measured = slope * d + offset + N(0, noise_std^2)  [+ Exp(nlos_bias_mean) with p_nlos]
A range is NaN when dropped or beyond the maximum range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
from numba import njit
from scipy.special import ndtri

from uwb_env.config import RangingConfig


@dataclass(frozen=True)
class RangeFit:
    """Linear fit of measured vs true distance: measured ~= slope * true + offset."""

    slope: float
    offset_m: float
    residual_std_m: float
    n_samples: int


def load_range_data(data_file: str = "dwm1001_los_ranges.csv") -> tuple[np.ndarray, np.ndarray]:
    """Return (true_m, measured_m) from a packaged file name or a filesystem path."""
    path = Path(data_file)
    if path.is_file():
        text = path.read_text()
    else:
        try:
            text = resources.files("uwb_env.data").joinpath(data_file).read_text()
        except FileNotFoundError:
            raise FileNotFoundError(
                f"ranging.data_file={data_file!r}: neither a file nor a packaged data file"
            ) from None
    rows = [line.split(",") for line in text.strip().splitlines()[1:] if line.strip()]
    data = np.array(rows, dtype=float)
    if data.ndim != 2 or data.shape[1] != 2 or len(data) < 3:
        raise ValueError(f"ranging.data_file={data_file!r}: expected >= 3 rows of true,measured")
    return data[:, 0], data[:, 1]


def fit_range_data(true_m: np.ndarray, measured_m: np.ndarray) -> RangeFit:
    """Ordinary least-squares line; residual std with n - 2 degrees of freedom."""
    design = np.column_stack([true_m, np.ones_like(true_m)])
    (slope, offset), *_ = np.linalg.lstsq(design, measured_m, rcond=None)
    residuals = measured_m - (slope * true_m + offset)
    std = float(np.sqrt(residuals @ residuals / (len(true_m) - 2)))
    return RangeFit(float(slope), float(offset), std, len(true_m))


def upper_tail_threshold(probability: float) -> float:
    """q with P(Z > q) = probability for a standard normal Z (inf for 0)."""
    if probability <= 0.0:
        return np.inf
    if probability >= 1.0:
        return -np.inf
    return float(-ndtri(probability))


class RangeModel:
    """Draws noisy ranges and corrects the known linear bias on the estimator side.

    Args:
        config: ranging configuration; the fit is computed from its data file at construction.
    """

    def __init__(self, config: RangingConfig | None = None):
        self.config = config or RangingConfig()
        self.fit = fit_range_data(*load_range_data(self.config.data_file))
        self.slope = self.fit.slope
        self.offset_m = self.fit.offset_m
        self.noise_std_m = (
            self.fit.residual_std_m if self.config.noise_std_m is None else self.config.noise_std_m
        )
        # Cached scalars: this sits in the simulator's hot loop.
        self._q_nlos = upper_tail_threshold(self.config.nlos_probability)
        self._nlos_mean = self.config.nlos_bias_mean_m
        self._q_drop = upper_tail_threshold(self.config.dropout_probability)
        self._max_range = self.config.max_range_m
        self._corrected_offset_m = self.offset_m + self.config.nlos_probability * self.config.nlos_bias_mean_m

    @property
    def corrected_noise_std_m(self) -> float:
        """Std of a single corrected (de-biased) range: noise / slope."""
        return self.noise_std_m / self.slope

    @property
    def corrected_range_std_m(self) -> float:
        """Std of a single corrected range with the NLOS excess included: the Gaussian noise
        and, with probability p, an Exp(mu) excess (its variance about the mean p mu that
        :meth:`correct` removes: p mu^2 (2 - p)), over the slope. The mixture's tail is
        heavier than a Gaussian's of this std."""
        p, mu = self.config.nlos_probability, self.config.nlos_bias_mean_m
        var = self.noise_std_m**2 + p * mu * mu * (2.0 - p)
        return float(np.sqrt(var) / (self.slope if self.config.correct_bias else 1.0))

    def measure(self, true_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Raw measured ranges for true distances ``true_m`` (any shape); NaN where lost."""
        true = np.asarray(true_m, dtype=float)
        # One Gaussian block: row 0 is the noise, rows 1-2 decide NLOS and dropout through
        # upper-tail thresholds (P(z > q) = p); one generator call and one compiled pass.
        z = rng.standard_normal((3,) + true.shape)
        out, nlos, n_nlos = _draw_ranges(true.reshape(-1), z.reshape(3, -1), self.slope, self.offset_m,
                                         self.noise_std_m, self._q_nlos)
        if n_nlos:
            out[nlos] += rng.exponential(self._nlos_mean, n_nlos)
        _drop(out, true.reshape(-1), z.reshape(3, -1), self._q_drop, self._max_range)
        return out.reshape(true.shape)

    def correct(self, measured_m: np.ndarray) -> np.ndarray:
        """Undo the known slope/offset and the NLOS excess's mean (p mu: every range carries it
        in expectation, so least squares over many pairs would otherwise stretch the whole
        shape): an unbiased estimate of the true distance."""
        if not self.config.correct_bias:
            return np.asarray(measured_m, dtype=float)
        return (np.asarray(measured_m, dtype=float) - self._corrected_offset_m) / self.slope

    def undo_linear_bias(self, measured_m: np.ndarray) -> np.ndarray:
        """(measured - offset) / slope: what firmware with calibrated antenna delays reports
        (the NLOS excess stays in: it is the radio path's, not the device's)."""
        return (np.asarray(measured_m, dtype=float) - self.offset_m) / self.slope

    def correct_matrix(self, matrix):
        """A round's :class:`~uwb_env.measurements.RangeMatrix` with means and stds corrected."""
        from uwb_env.measurements import RangeMatrix

        return RangeMatrix(self.correct(matrix.mean_m), self.correct_std(matrix.std_m), matrix.count)

    def correct_std(self, std_m: np.ndarray) -> np.ndarray:
        """Map a measured-range std to the std of the corrected range."""
        if not self.config.correct_bias:
            return np.asarray(std_m, dtype=float)
        return np.asarray(std_m, dtype=float) / self.slope


@njit(cache=True)
def _draw_ranges(true, z, slope, offset, noise_std, q_nlos):
    """slope * true + offset + noise, and where the NLOS normal exceeds its threshold."""
    n = true.shape[0]
    out = np.empty(n)
    nlos = np.zeros(n, dtype=np.bool_)
    count = 0
    for i in range(n):
        out[i] = slope * true[i] + offset + noise_std * z[0, i]
        if z[1, i] > q_nlos:
            nlos[i] = True
            count += 1
    return out, nlos, count


@njit(cache=True)
def _drop(out, true, z, q_drop, max_range):
    """Lost readings (dropout, beyond the maximum range) become NaN."""
    for i in range(out.shape[0]):
        if z[2, i] > q_drop or true[i] > max_range:
            out[i] = np.nan


@njit(cache=True)
def planar_distances(tags, anchors):
    """(S, M, N) distances between tags (S, M, >= 2) and anchors (S, N, >= 2) over the first two
    axes: ``np.linalg.norm(tags[:, :, None, :2] - anchors[:, None, :, :2], axis=-1)``'s numbers
    without its (S, M, N, 2) temporaries."""
    s_count, m_count, n_count = tags.shape[0], tags.shape[1], anchors.shape[1]
    out = np.empty((s_count, m_count, n_count))
    for s in range(s_count):
        for m in range(m_count):
            for k in range(n_count):
                dx = tags[s, m, 0] - anchors[s, k, 0]
                dy = tags[s, m, 1] - anchors[s, k, 1]
                out[s, m, k] = math.sqrt(dx * dx + dy * dy)
    return out
