"""The pinhole camera of the workbench (OpenCV convention).

Camera frame: x right, y down, z forward. A world point X (projected metres, z up)
maps to the camera frame by ``x_cam = R @ X + t``, then to pixels by ``K`` (and the
optional OpenCV distortion k1 k2 p1 p2 k3). Pixel centres are at integer
coordinates: the top-left pixel's centre is (0, 0), as in OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

# OpenCV's default (5 iterations) leaves 1e-3 px errors at the image corners
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class Camera:
    """A calibrated pinhole camera.

    Attributes
    ----------
    K : (3, 3) ndarray
        Intrinsics, pixels.
    R : (3, 3) ndarray
        World-to-camera rotation.
    t : (3,) ndarray
        World-to-camera translation, metres.
    width, height : int
        Image size in pixels.
    distortion : (5,) ndarray
        OpenCV k1 k2 p1 p2 k3 (zeros for an ideal pinhole).
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @property
    def center(self) -> np.ndarray:
        """Projection centre in world coordinates, (3,) metres."""
        return -self.R.T @ self.t

    @property
    def viewing_direction(self) -> np.ndarray:
        """Unit optical axis in world coordinates, (3,)."""
        return self.R[2].copy()

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.distortion != 0))

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points to (N, 3) camera-frame points."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to pixels.

        Parameters
        ----------
        points : (N, 3) ndarray
            World coordinates, metres.

        Returns
        -------
        uv : (N, 2) ndarray
            Pixel coordinates (column, row); NaN for points behind the camera.
        depth : (N,) ndarray
            z-depth along the optical axis, metres (negative behind the camera).
        """
        pc = self.world_to_camera(points)
        depth = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack(self.project_camera_frame(pc[:, 0], pc[:, 1], depth), axis=1)
        uv[depth <= 0] = np.nan
        return uv, depth

    def project_camera_frame(self, x, y, z) -> tuple[np.ndarray, np.ndarray]:
        """Pixel columns and rows (u, v) of camera-frame points (``x``, ``y``, ``z``:
        arrays of one shape, metres), distortion applied; meaningless where ``z <= 0``
        (behind the camera: the caller masks them)."""
        x, y = x / z, y / z
        if self.has_distortion:
            x, y = _distort(x, y, self.distortion)
        K = self.K
        return K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]

    def pixel_rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays through pixels, scaled so that the ray parameter is the z-depth.

        Parameters
        ----------
        uv : (N, 2) ndarray
            Pixel coordinates (column, row).

        Returns
        -------
        origin : (3,) ndarray
            The camera centre (world).
        directions : (N, 3) ndarray
            World directions whose camera-frame z component is 1, so that
            ``origin + d * directions`` is the point at z-depth ``d``.
        """
        uv = np.asarray(uv, dtype=np.float64)
        if self.has_distortion:
            xy = _undistort(uv.reshape(-1, 1, 2), self.K, self.distortion).reshape(-1, 2)
        else:
            Kinv = np.linalg.inv(self.K)
            xy = uv @ Kinv[:2, :2].T + Kinv[:2, 2]
        d_cam = np.column_stack([xy, np.ones(len(xy))])
        return self.center, d_cam @ self.R

    def pixel_grid_rays(
        self, step: int = 1, window: tuple[slice, slice] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rays through every ``step``-th pixel centre, row-major.

        With ``window`` (rows, columns), the rays of its pixels alone: the same values
        as the whole image's at those pixels.

        Returns the origin (3,) and directions (H*W, 3) (the window's pixels), as
        :meth:`pixel_rays`.
        """
        rows, cols = window if window is not None else (slice(None), slice(None))
        rows, cols = rows.indices(self.height)[:2], cols.indices(self.width)[:2]
        u = np.arange(*cols, step, dtype=np.float64)
        v = np.arange(*rows, step, dtype=np.float64)
        if self.has_distortion:
            uu, vv = np.meshgrid(u, v)
            return self.pixel_rays(np.column_stack([uu.ravel(), vv.ravel()]))
        # without distortion a ray is linear in (u, v): a sum of a row and a column term
        M = self.R.T @ np.linalg.inv(self.K)  # camera z of every direction stays 1
        dirs = np.empty((len(v), len(u), 3))
        for k in range(3):  # one axis at a time: NumPy's loops run along rows, not triples
            dirs[..., k] = (v[:, None] * M[k, 1] + M[k, 2]) + u[None, :] * M[k, 0]
        return self.center, dirs.reshape(-1, 3)

    def to_dict(self) -> dict:
        """The camera as the fields of a scene.json view."""
        d = {
            "K": np.round(self.K, 9).tolist(),
            "R": np.round(self.R, 12).tolist(),
            "t": np.round(self.t, 9).tolist(),
            "width": int(self.width),
            "height": int(self.height),
        }
        if self.has_distortion:
            d["distortion"] = self.distortion.tolist()
        return d


def framing_cameras(cameras: list[Camera], vertices: np.ndarray) -> list[int]:
    """The cameras whose image can hold some point of the box around ``vertices`` (V, 3):
    the box's projection lies inside the hull of its projected corners, so a view whose
    frame misses those corners' bounding rectangle (and a margin for the lens's
    distortion) sees none of it. A city's flight has
    hundreds of views and a building is in a few dozen: the others would only fill the
    texture's (texels x views) arrays with nothing seen. Every camera at once: a task
    asks this of the flight's hundreds of views several times."""
    if not cameras:
        return []
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])  # fmt: skip
    R = np.stack([c.R for c in cameras])  # (C, 3, 3)
    t = np.stack([c.t for c in cameras])
    K = np.stack([c.K for c in cameras])
    size = np.array([[c.width, c.height] for c in cameras], float)
    pc = np.einsum("nj,cij->cni", corners, R) + t[:, None, :]  # (C, 8, 3)
    depth = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = pc[..., 0] / depth, pc[..., 1] / depth
        dist = np.stack([c.distortion for c in cameras]).T[:, :, None]  # (5, C, 1)
        x, y = _distort(x, y, dist)  # zero coefficients leave them as they are
        u = K[:, 0, 0, None] * x + K[:, 0, 1, None] * y + K[:, 0, 2, None]
        v = K[:, 1, 1, None] * y + K[:, 1, 2, None]
    front, behind = (depth > 0).any(axis=1), (depth <= 0).any(axis=1)
    m = 0.1 * size.max(axis=1)  # lens distortion bends the hull a little
    with np.errstate(invalid="ignore"):
        overlaps = ((u.max(axis=1) >= -m) & (u.min(axis=1) <= size[:, 0] - 1 + m)
                    & (v.max(axis=1) >= -m) & (v.min(axis=1) <= size[:, 1] - 1 + m))  # fmt: skip
    # a box straddling a camera's plane is kept, to be safe; one wholly behind is not
    keep = front & (behind | overlaps)
    return [int(k) for k in np.flatnonzero(keep)]


def steepest_sight(cameras: list[Camera], lo: np.ndarray, hi: np.ndarray) -> float:
    """The largest horizontal-to-vertical ratio of a line from a point of the box ``lo``
    to ``hi`` ((3,) world metres) to the centre of a camera whose frame can hold it
    (:func:`framing_cameras`); inf if such a centre stands no higher than the box's top,
    0 if no frame holds it.

    A point of the box sees such a camera along a line no flatter than this, so only
    what stands within (its top above the point) x this of it, horizontally, can hide
    it. The flight's geometry bounds it, not the views' fields: an oblique frame's top
    edge nears the horizon, but the points it shows there lie far beyond the box.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    framing = framing_cameras(cameras, np.array([lo, hi]))
    if not framing:
        return 0.0
    c = np.array([cameras[k].center for k in framing])
    up = c[:, 2] - hi[2]
    if (up <= 0).any():
        return float("inf")
    dx = np.maximum(np.abs(c[:, 0] - lo[0]), np.abs(c[:, 0] - hi[0]))
    dy = np.maximum(np.abs(c[:, 1] - lo[1]), np.abs(c[:, 1] - hi[1]))
    return float(np.max(np.hypot(dx, dy) / up))


def _undistort(uv: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
        return cv2.undistortPointsIter(uv, K, dist, None, None, _UNDISTORT_CRITERIA)
    return cv2.undistortPoints(uv, K, dist, criteria=_UNDISTORT_CRITERIA)  # OpenCV 5


def _distort(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def look_at_rotation(forward: np.ndarray, up_hint: np.ndarray | None = None) -> np.ndarray:
    """World-to-camera rotation of a camera looking along ``forward``.

    The image x axis is horizontal (``forward x up``); for a camera looking
    straight down it points east, so that north is up in the image.
    """
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if up_hint is None else np.asarray(up_hint, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # nadir: east is image right
        x = np.array([1.0, 0.0, 0.0])
        x = x - z * (x @ z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` radians about ``axis`` (Rodrigues)."""
    rvec = np.asarray(axis, dtype=np.float64)
    rvec = rvec / np.linalg.norm(rvec) * angle
    return cv2.Rodrigues(rvec)[0]
