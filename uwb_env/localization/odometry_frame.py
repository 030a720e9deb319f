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
    """The transform from the odometry frame to the first reference calibration's frame.

    ``rotation`` (2, 2) orthogonal (a reflection when ``reflected``); ``alignment`` (2, 2) the
    orthogonal map from the first reference's frame to the last later calibration's (a
    reflection where a later calibration came out mirrored against its reference), so that
    ``current = alignment @ rotation`` maps odometry displacements into the frame of the latest
    calibration; ``angle_std_rad`` from the chi-square's curvature at the optimum; ``chi2`` on
    ``dof`` = sum over intervals of (2 N - 3), less one; ``rival_chi2`` the best fit outside the
    optimum's basin (the other handedness, or another local minimum over the angle);
    ``alignment_margin_chi2`` how much worse the other handedness of the worst-decided
    interval's alignment fits. ``status``:

    - ``ok``: a fit the noise explains, an angle known to ``max_angle_std_rad``, every rival and
      every interval's other alignment handedness at least ``margin_chi2`` worse;
    - ``ambiguous``: a rival (or an alignment's handedness) within the margin;
    - ``unobservable``: the angle is not pinned down (the team moved almost rigidly: ranges
      cannot see a rigid motion);
    - ``poor_fit``: even the best transform leaves a chi-square the noise cannot explain (a
      calibration or the odometry is wrong, or the robots do not share one odometry frame).
    """

    rotation: np.ndarray
    reflected: bool
    angle_rad: float
    angle_std_rad: float
    alignment: np.ndarray
    chi2: float
    dof: int
    rival_chi2: float
    alignment_margin_chi2: float
    status: str

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def current(self) -> np.ndarray:
        """Odometry frame -> the latest calibration's frame."""
        return self.alignment @ self.rotation


def _complex(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    return points[..., 0] + 1j * points[..., 1]


def planar_orthogonal(angle: float, reflected: bool) -> np.ndarray:
    """rot(angle), times diag(1, -1) first when ``reflected``: e^{i angle} z, or of conj(z)."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    return rot @ np.diag([1.0, -1.0]) if reflected else rot


def chained_chi2(angles: np.ndarray, reflected: bool, intervals: list) -> tuple:
    """Summed chi-square over consecutive intervals for the transform (``angles``, any 1-D
    array; ``reflected``) into the first reference's frame, carried from interval to interval
    by each one's best alignment.

    In one interval, with x_i = ref_i + Q d_i (Q d = e^{i angle} d, or of conj(d) when
    reflected): min over a proper rotation phi and translation t of sum w_i |later_i - e^{i phi}
    x_i - t|^2 = Sxx + Syy - 2 |sum w_i conj(xc_i) yc_i| (centred by the weighted means), and
    over an improper one (e^{i phi} conj(x)) the same with |sum w_i xc_i yc_i|; the better one
    carries Q into the later frame (proper: the angle plus phi; improper: phi minus the angle,
    the handedness flipped). Returns (total chi2, the smallest gap between an interval's two
    alignment handednesses, the carried angle and handedness)."""
    theta = np.array(angles, dtype=float)
    hand = np.full(theta.shape, bool(reflected))
    total = np.zeros(theta.shape)
    margin = np.full(theta.shape, np.inf)
    for z_ref, z_lat, z_disp, w in intervals:
        d = np.where(hand[:, None], np.conj(z_disp)[None], z_disp[None])
        x = z_ref[None] + np.exp(1j * theta)[:, None] * d
        wsum = w.sum()
        xc = x - (x * w).sum(-1, keepdims=True) / wsum
        yc = z_lat - (z_lat * w).sum() / wsum
        base = (w * np.abs(xc) ** 2).sum(-1) + (w * np.abs(yc) ** 2).sum()
        proper, improper = (w * np.conj(xc) * yc).sum(-1), (w * xc * yc).sum(-1)
        chi_p, chi_m = base - 2.0 * np.abs(proper), base - 2.0 * np.abs(improper)
        mirrored = chi_m < chi_p
        total += np.maximum(np.minimum(chi_p, chi_m), 0.0)
        margin = np.minimum(margin, np.abs(chi_p - chi_m))
        phi = np.where(mirrored, np.angle(improper), np.angle(proper))
        theta = np.where(mirrored, phi - theta, theta + phi)
        hand = np.where(mirrored, ~hand, hand)
    return total, margin, theta, hand


def prepared_interval(reference, later, displacement, var_m2) -> tuple:
    ref, lat, disp = (np.asarray(a, dtype=float) for a in (reference, later, displacement))
    var = np.asarray(var_m2, dtype=float)
    n = ref.shape[0] if ref.ndim == 2 else 0
    for name, arr in (("reference", ref), ("later", lat), ("displacement", disp)):
        if arr.shape != (n, 2):
            raise ValueError(f"{name}: shape {arr.shape}, expected ({n}, 2) (planar positions of the same anchors)")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}: non-finite entries")
    if var.shape != (n,) or not (np.isfinite(var).all() and (var > 0).all()):
        raise ValueError(f"var_m2: expected {n} positive finite variances, got {var!r}")
    if n < 3:
        raise ValueError(f"reference: {n} anchors; the transform needs at least 3")
    return _complex(ref), _complex(lat), _complex(disp), 2.0 / var  # isotropic per-axis variance var / 2


def fit_odometry_rotation(reference: np.ndarray, later: np.ndarray, displacement: np.ndarray,
                          var_m2: np.ndarray, margin_chi2: float = 16.0,
                          max_angle_std_rad: float = np.deg2rad(5.0), grid: int = 720) -> OdometryFrameFit:
    """Fit the odometry frame's transform from two calibrations and the odometry between them
    (:func:`fit_odometry_rotation_chain` of one interval).

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
    return fit_odometry_rotation_chain([(reference, later, displacement, var_m2)], margin_chi2, max_angle_std_rad,
                                       grid)


def fit_odometry_rotation_chain(intervals: list, margin_chi2: float = 16.0,
                                max_angle_std_rad: float = np.deg2rad(5.0), grid: int = 720) -> OdometryFrameFit:
    """One transform for consecutive intervals: ``intervals`` a list of (reference, later,
    displacement, var_m2) as :func:`fit_odometry_rotation` takes, each interval's ``later`` the
    next one's ``reference`` (the same calibration, the same frame). Every interval adds
    evidence on the one transform, with only its own odometry drift in its variance; robots
    whose odometry frames differ fit no single transform across them (``poor_fit``)."""
    if not intervals:
        raise ValueError("intervals: at least one (reference, later, displacement, var_m2)")
    prepared = [prepared_interval(*interval) for interval in intervals]
    angles = np.linspace(-np.pi, np.pi, grid, endpoint=False)
    step = angles[1] - angles[0]
    curves = {reflected: chained_chi2(angles, reflected, prepared)[0] for reflected in (False, True)}
    reflected = min(curves, key=lambda r: curves[r].min())
    curve = curves[reflected]
    k = int(np.argmin(curve))

    def f(a: float) -> float:
        return float(chained_chi2(np.array([a]), reflected, prepared)[0][0])

    res = minimize_scalar(f, bounds=(angles[k] - step, angles[k] + step), method="bounded", options={"xatol": 1e-9})
    angle = float(res.x) if res.fun <= curve[k] else float(angles[k])
    best = min(float(res.fun), float(curve[k]))
    h = 1e-3
    curvature = (f(angle + h) - 2.0 * best + f(angle - h)) / (h * h)
    angle_std = float(np.sqrt(2.0 / curvature)) if curvature > 0 else np.inf
    # rivals: the other handedness anywhere, and this one's other local minima (the optimum's own
    # basin rises smoothly away from it and is no rival: its width is the angle's std)
    minima = (curve <= np.roll(curve, 1)) & (curve <= np.roll(curve, -1))
    minima[k] = False
    rival = min(float(curves[not reflected].min()), float(curve[minima].min()) if minima.any() else np.inf)
    _, gap, carried, carried_hand = chained_chi2(np.array([angle]), reflected, prepared)
    dof = sum(2 * len(p[0]) - 3 for p in prepared) - 1
    if dof > 0 and best > chi2_dist.ppf(0.999, dof):
        status = "poor_fit"
    elif not angle_std <= max_angle_std_rad:
        status = "unobservable"
    elif rival - best < margin_chi2 or gap[0] < margin_chi2:
        status = "ambiguous"
    else:
        status = "ok"
    wrapped = float(np.angle(np.exp(1j * angle)))
    rotation = planar_orthogonal(wrapped, reflected)
    current = planar_orthogonal(float(carried[0]), bool(carried_hand[0]))
    return OdometryFrameFit(rotation=rotation, reflected=reflected, angle_rad=wrapped, angle_std_rad=angle_std,
                            alignment=current @ rotation.T, chi2=best, dof=dof, rival_chi2=rival,
                            alignment_margin_chi2=float(gap[0]), status=status)
