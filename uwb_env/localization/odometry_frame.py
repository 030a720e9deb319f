"""The rotation between the robots' odometry frame and the calibration's estimate frame (planar).

On hardware the anchor estimates live in the first calibration's paper frame (anchor 0 at the
origin, anchor 1 on +x, anchor 2 in +y), while the robots report their displacements in their
odometry frame. The two differ by an unknown rotation, and possibly a reflection (the paper
frame's handedness follows the anchors, not the world). A displacement added without that
transform moves the estimate the wrong way.

Ranging alone cannot tell the transform: a rigid motion of the whole team leaves every range
unchanged. A motion that changes the team's *shape* does: with the positions ``reference``
solved by one calibration and the odometry displacements ``d`` since then, only the right
transform ``Q`` makes ``reference + Q d`` congruent to the positions a later calibration solves.
:func:`fit_odometry_rotation` scores every ``Q`` (both handednesses, the angle on a grid then
refined) by the weighted chi-square of that congruence, minimized over the rigid motion between
the two calibrations' frames (a weighted Procrustes problem with a closed form), and says
whether the data decide it.

Pure numpy/scipy; no RL imports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import chi2 as chi2_dist

ODOMETRY_FRAME_STATUSES = ("ok", "ambiguous", "unobservable", "poor_fit")


@dataclass(frozen=True)
class OdometryFrameFit:
    """The transform from the odometry frame to the reference calibration's frame.

    ``rotation`` (2, 2) orthogonal (a reflection when ``reflected``); ``alignment`` (2, 2) the
    proper rotation from the reference calibration's frame to the later one's;
    ``angle_std_rad`` from the chi-square's curvature at the optimum; ``chi2`` on ``dof`` = 2N - 4
    degrees of freedom; ``rival_chi2`` the best fit outside the optimum's basin (the other
    handedness, or another local minimum over the angle). ``status``:

    - ``ok``: a fit the noise explains, an angle known to ``max_angle_std_rad`` and every rival
      at least ``margin_chi2`` worse;
    - ``ambiguous``: a rival within the margin (e.g. a motion that is nearly a reflection of
      itself);
    - ``unobservable``: the angle is not pinned down (the team moved almost rigidly: ranges
      cannot see a rigid motion);
    - ``poor_fit``: even the best transform leaves a chi-square the noise cannot explain (a
      calibration or the odometry is wrong).
    """

    rotation: np.ndarray
    reflected: bool
    angle_rad: float
    angle_std_rad: float
    alignment: np.ndarray
    chi2: float
    dof: int
    rival_chi2: float
    status: str

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def _complex(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    return points[..., 0] + 1j * points[..., 1]


def _matrix(angle: float, reflected: bool) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    return rot @ np.diag([1.0, -1.0]) if reflected else rot


def _chi2_curve(angles: np.ndarray, z_ref, z_later, z_disp, w) -> tuple[np.ndarray, np.ndarray]:
    """chi2 over ``angles`` (any shape) for displacements ``z_disp`` already reflected or not,
    and the phase of the best rigid rotation from the reference's frame to the later one's.

    For x_i = ref_i + e^{i angle} d_i: min over the rotation phi and translation t of
    sum w_i |later_i - e^{i phi} x_i - t|^2 = Sxx + Syy - 2 |sum w_i conj(xc_i) yc_i| (centred by
    the weighted means), the best phi being that sum's argument."""
    x = z_ref + np.exp(1j * np.asarray(angles))[..., None] * z_disp
    wsum = w.sum()
    xc = x - (x * w).sum(-1, keepdims=True) / wsum
    yc = z_later - (z_later * w).sum() / wsum
    cross = (w * np.conj(xc) * yc).sum(-1)
    value = (w * np.abs(xc) ** 2).sum(-1) + (w * np.abs(yc) ** 2).sum() - 2.0 * np.abs(cross)
    return np.maximum(value, 0.0), np.angle(cross)


def fit_odometry_rotation(reference: np.ndarray, later: np.ndarray, displacement: np.ndarray,
                          var_m2: np.ndarray, margin_chi2: float = 16.0,
                          max_angle_std_rad: float = np.deg2rad(5.0), grid: int = 720) -> OdometryFrameFit:
    """Fit the odometry frame's transform from two calibrations and the odometry between them.

    Args:
        reference: (N, 2) positions one calibration solved (its frame: the one the transform
            maps into).
        later: (N, 2) positions a later calibration solved (any frame: a rigid motion away).
        displacement: (N, 2) each anchor's odometry displacement between the two, in the
            odometry frame.
        var_m2: (N,) each anchor's variance (summed over both axes) of
            ``later - (reference + Q displacement)`` up to the rigid motion: both calibrations'
            variances plus the odometry's drift between them.
        margin_chi2: how much worse every rival must fit for ``ok``.
        max_angle_std_rad: the largest angle std still ``ok``.
        grid: angles per handedness on the first pass.
    """
    ref, lat, disp = (np.asarray(a, dtype=float) for a in (reference, later, displacement))
    var = np.asarray(var_m2, dtype=float)
    n = ref.shape[0]
    for name, arr in (("reference", ref), ("later", lat), ("displacement", disp)):
        if arr.shape != (n, 2):
            raise ValueError(f"{name}: shape {arr.shape}, expected ({n}, 2) (planar positions of the same anchors)")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}: non-finite entries")
    if var.shape != (n,) or not (np.isfinite(var).all() and (var > 0).all()):
        raise ValueError(f"var_m2: expected {n} positive finite variances, got {var!r}")
    if n < 3:
        raise ValueError(f"reference: {n} anchors; the transform needs at least 3")
    w = 2.0 / var  # isotropic per-axis variance var / 2
    z_ref, z_lat = _complex(ref), _complex(lat)
    angles = np.linspace(-np.pi, np.pi, grid, endpoint=False)
    step = angles[1] - angles[0]
    curves = {}
    for reflected in (False, True):
        z_disp = _complex(disp)
        z_disp = np.conj(z_disp) if reflected else z_disp
        curves[reflected] = (z_disp, _chi2_curve(angles, z_ref, z_lat, z_disp, w)[0])
    best_reflected = min(curves, key=lambda r: curves[r][1].min())
    z_disp, curve = curves[best_reflected]
    k = int(np.argmin(curve))

    def f(a: float) -> float:
        return float(_chi2_curve(np.array(a), z_ref, z_lat, z_disp, w)[0])

    res = minimize_scalar(f, bounds=(angles[k] - step, angles[k] + step), method="bounded",
                          options={"xatol": 1e-9})
    angle = float(res.x) if res.fun <= curve[k] else float(angles[k])
    best = min(float(res.fun), float(curve[k]))
    h = 1e-3
    curvature = (f(angle + h) - 2.0 * best + f(angle - h)) / (h * h)
    angle_std = float(np.sqrt(2.0 / curvature)) if curvature > 0 else np.inf
    # rivals: the other handedness anywhere, and this one's other local minima (the optimum's own
    # basin rises smoothly away from it and is no rival: its width is the angle's std)
    minima = (curve <= np.roll(curve, 1)) & (curve <= np.roll(curve, -1))
    minima[k] = False
    rival = min(float(curves[not best_reflected][1].min()), float(curve[minima].min()) if minima.any() else np.inf)
    phase = float(_chi2_curve(np.array(angle), z_ref, z_lat, z_disp, w)[1])
    dof = 2 * n - 4
    if dof > 0 and best > chi2_dist.ppf(0.999, dof):
        status = "poor_fit"
    elif not angle_std <= max_angle_std_rad:
        status = "unobservable"
    elif rival - best < margin_chi2:
        status = "ambiguous"
    else:
        status = "ok"
    wrapped = float(np.angle(np.exp(1j * angle)))
    return OdometryFrameFit(rotation=_matrix(wrapped, best_reflected), reflected=best_reflected, angle_rad=wrapped,
                            angle_std_rad=angle_std, alignment=_matrix(phase, False), chi2=best, dof=dof,
                            rival_chi2=rival, status=status)
