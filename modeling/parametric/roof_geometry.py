"""Roof geometry (the variational paper, eq. 5, 6, 11, 12): the five-parameter roof of a
rectangular wing fitted to the DSM, and its roof type.

On a wing [u0, u1] x [v0, v1] the four roof planes rise from its four sides:
d_1 = u - u0, d_2 = v - v0, d_3 = u1 - u, d_4 = v1 - v are the horizontal distances to
them, and the roof stands h_r = min_k d_k tan(omega_k) above the main height h_m (eq. 5).
An angle near 90 degrees is a vertical plane (a gable end: that side never is the
minimum); an angle of 0 a flat roof. Eq. 6's squared error is minimised over
(h_m, omega_1..4) by a bounded trust-region method with the gradient of eq. 11, through
the smooth minimum of eq. 12, from the best of a few closed-form starts (flat, shed,
gable, hipped at several pitches); a robust loss keeps the walls' cells and chimneys
from pulling the planes.

The paper derives two roofs the four planes cannot make: a platform, and a gambrel. Here
both are a cap: h_r = min(min_k d_k tan(omega_k), c), a flat top at c above h_m, fitted
as a sixth parameter when it explains the DSM clearly better (a mansard: steep lower
faces under a flat or nearly flat top; a platform: shallow ones).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize

SMOOTH_M = 0.02  # eq. 12's min made smooth: sqrt((a - b)^2 + SMOOTH_M^2)
MAX_DEG = 89.5  # the steepest fitted plane; from VERTICAL_DEG on it is a vertical end
VERTICAL_DEG = 75.0
FLAT_DEG = 5.0
STEEP_DEG = 55.0  # a cap over faces this steep is a mansard (gambrel), else a platform
ASYMMETRY_DEG = 10.0  # opposite sloped sides this different make a dissymmetric roof
_CAP_GAIN = 0.7  # the cap is kept when it brings the robust cost under this share
_PITCHES = (15.0, 25.0, 35.0, 45.0, 55.0)
_V = MAX_DEG - 1.0


def side_distances(u: np.ndarray, v: np.ndarray, wing: np.ndarray) -> np.ndarray:
    """(4, N) horizontal distances d_1..d_4 from cells at (u, v) to the wing's sides."""
    u0, u1, v0, v1 = wing
    return np.stack([u - u0, v - v0, u1 - u, v1 - v])


def smooth_min(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 12's min(a, b) = (a + b - sqrt((a - b)^2)) / 2, smoothed; with its derivatives
    with respect to a and b."""
    s = np.sqrt((a - b) ** 2 + SMOOTH_M**2)
    return 0.5 * (a + b - s), 0.5 * (1 - (a - b) / s), 0.5 * (1 + (a - b) / s)


def roof_heights(d: np.ndarray, omega: np.ndarray, cap: float | None = None):
    """Eq. 5 through eq. 12's smooth minimum: h_r (N,) and dh_r/domega (4, N) (and
    dh_r/dcap (N,) when there is a cap).

    d : (4, N) side distances, metres; omega : (4,) radians; cap : metres above h_m."""
    x = d * np.tan(omega)[:, None]
    m12, a1, a2 = smooth_min(x[0], x[1])
    m34, a3, a4 = smooth_min(x[2], x[3])
    h, b12, b34 = smooth_min(m12, m34)
    dx = np.stack([b12 * a1, b12 * a2, b34 * a3, b34 * a4])
    grad = dx * d / np.cos(omega)[:, None] ** 2  # eq. 11: d(d tan w)/dw = d sec^2 w
    if cap is None:
        return h, grad, None
    hc, bh, bc = smooth_min(h, np.full_like(h, cap))
    return hc, grad * bh, bc


def _residuals(params, d, z, capped):
    cap = params[5] if capped else None
    h, grad, dcap = roof_heights(d, params[1:5], cap)
    r = params[0] + h - z
    jac = np.column_stack([np.ones_like(r), grad.T, *([dcap] if capped else [])])
    return r, jac


@dataclass
class RoofFit:
    """A wing's fitted roof.

    Attributes
    ----------
    z_main : float
        Absolute height of the main plane P_m (h_m above the ground), metres.
    omega : (4,) float
        Angles of the planes rising from sides u0, v0, u1, v1, radians.
    cap : float or None
        Height of a flat top above P_m, metres (platform, mansard).
    rms : float
        Root mean square of the residuals over the fitted cells, metres.
    cost : float
        Mean robust cost (eq. 6 under the soft-L1 loss), metres^2.
    evaluations : int
    """

    z_main: float
    omega: np.ndarray
    cap: float | None
    rms: float
    cost: float
    evaluations: int

    def snapped(self) -> np.ndarray:
        """tan(omega) with vertical ends at infinity and flat planes at 0."""
        deg = np.degrees(self.omega)
        t = np.tan(self.omega)
        t[deg >= VERTICAL_DEG] = np.inf
        t[deg <= FLAT_DEG] = 0.0
        return t


def _robust_cost(r: np.ndarray, scale: float) -> float:
    return float(np.mean(2 * scale**2 * (np.sqrt(1 + (r / scale) ** 2) - 1)))


def _starts() -> list[np.ndarray]:
    out = [np.zeros(4)]
    for p in _PITCHES:
        out += [np.array(a) for a in ((p, _V, _V, _V), (_V, p, _V, _V), (_V, _V, p, _V),
                                      (_V, _V, _V, p), (_V, p, _V, p), (p, _V, p, _V),
                                      (p, p, p, p))]  # fmt: skip
    return [np.radians(a) for a in out]


def fit_roof(d: np.ndarray, z: np.ndarray, robust_m: float, z_main: float | None = None) -> RoofFit:
    """Eq. 6 minimised for one wing: (h_m, omega_1..4), then with a cap if it pays.

    Parameters
    ----------
    d : (4, N) side distances of the wing's cells, metres
    z : (N,) DSM heights at those cells, metres
    robust_m : float
        Scale of the soft-L1 loss, metres.
    z_main : float, optional
        The main height, held fixed (the paper's h_m is one per building).
    """
    best, best_cost = None, np.inf
    for omega in _starts():  # closed-form starts: the main height is the median offset
        h, _, _ = roof_heights(d, omega)
        zm = float(np.median(z - h)) if z_main is None else z_main
        c = _robust_cost(zm + h - z, robust_m)
        if c < best_cost:
            best, best_cost = np.concatenate([[zm], omega]), c
    free = z_main is None
    lo = np.r_[-np.inf if free else z_main - 1e-6, np.zeros(4)]
    hi = np.r_[np.inf if free else z_main + 1e-6, np.full(4, np.radians(MAX_DEG))]
    fit = _solve(best, d, z, robust_m, lo, hi, capped=False)
    rise = float(np.percentile(z, 95) - fit.z_main)
    if rise > 2 * robust_m:  # room for a cap
        starts = [np.r_[fit.z_main, fit.omega, 0.8 * rise],
                  np.r_[fit.z_main, np.full(4, np.radians(70.0)), 0.8 * rise]]  # fmt: skip
        lo_c, hi_c = np.r_[lo, 0.0], np.r_[hi, np.inf]
        capped = min((_solve(s, d, z, robust_m, lo_c, hi_c, capped=True) for s in starts),
                     key=lambda f: f.cost)  # fmt: skip
        if capped.cost < _CAP_GAIN * fit.cost and capped.cap is not None:
            h_free, _, _ = roof_heights(d, capped.omega)
            if np.mean(h_free > capped.cap) >= 0.1:  # the top covers a tenth of the wing
                return capped
    return fit


def _solve(x0, d, z, robust_m, lo, hi, capped: bool) -> RoofFit:
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
    res = optimize.least_squares(
        lambda p: _residuals(p, d, z, capped)[0], x0,
        jac=lambda p: _residuals(p, d, z, capped)[1], bounds=(lo, hi), loss="soft_l1",
        f_scale=robust_m, max_nfev=60,
    )  # fmt: skip
    r = _residuals(res.x, d, z, capped)[0]
    cap = float(res.x[5]) if capped else None
    rms = float(np.sqrt(np.mean(r**2)))
    return RoofFit(float(res.x[0]), res.x[1:5].copy(), cap, rms, _robust_cost(r, robust_m),
                   int(res.nfev))  # fmt: skip


def _side_heights(d: np.ndarray, fit: RoofFit) -> np.ndarray:
    """(4, N) d_k tan(omega_k) of the snapped planes: infinite for a vertical end."""
    t = fit.snapped()
    return np.where(np.isinf(t)[:, None], np.inf, d * np.where(np.isinf(t), 0, t)[:, None])


def exact_heights(d: np.ndarray, fit: RoofFit) -> np.ndarray:
    """(N,) roof heights above P_m of the model as meshed: the exact minimum of the
    snapped planes (vertical ends dropped, flat planes at 0) and the cap."""
    h = _side_heights(d, fit).min(axis=0)
    if not np.isfinite(h).all():  # every side vertical: a flat top at the cap or P_m
        h = np.where(np.isfinite(h), h, fit.cap or 0.0)
    return np.minimum(h, fit.cap) if fit.cap is not None else h


def roof_type(fit: RoofFit, wing: np.ndarray, min_share: float = 0.08) -> str:
    """The roof type the angles make (the variational paper, Fig. 2 and section II).

    flat: no sloped plane; shed: one; gable: two opposite; hipped: three or four along a
    ridge; pyramid: four meeting in a point; dissymmetric: opposite sloped planes more
    than ASYMMETRY_DEG apart, or two adjacent ones; with a cap: mansard (over faces
    steeper than STEEP_DEG), else platform. A plane counts when it tops at least
    ``min_share`` of the wing.
    """
    u0, u1, v0, v1 = wing
    uu, vv = np.meshgrid(np.linspace(u0, u1, 41), np.linspace(v0, v1, 41))
    d = side_distances(uu.ravel(), vv.ravel(), wing)
    owner = np.argmin(_side_heights(d, fit), axis=0)
    h = exact_heights(d, fit)
    if fit.cap is not None:
        owner = np.where(h >= fit.cap - 1e-6, 4, owner)
    share = np.bincount(owner, minlength=5) / owner.size
    deg = np.degrees(fit.omega)
    sloped = [k for k in range(4) if share[k] >= min_share and FLAT_DEG < deg[k] < VERTICAL_DEG]
    if not sloped or h.max() - h.min() < 0.3:
        return "flat"
    if fit.cap is not None and share[4] >= min_share:
        return "mansard" if np.mean(deg[sloped]) >= STEEP_DEG else "platform"
    pairs = [(0, 2), (1, 3)]
    for a, b in pairs:
        if a in sloped and b in sloped and abs(deg[a] - deg[b]) > ASYMMETRY_DEG:
            return "dissymmetric"
    if len(sloped) == 1:
        return "shed"
    if len(sloped) == 2:
        return "gable" if (sloped[1] - sloped[0]) == 2 else "dissymmetric"
    if len(sloped) == 4:
        top = h >= h.max() - 0.05 * max(h.max(), 1e-6)
        span_u, span_v = np.ptp(uu.ravel()[top]), np.ptp(vv.ravel()[top])
        if max(span_u, span_v) < 0.15 * max(u1 - u0, v1 - v0):
            return "pyramid"
    return "hipped"
