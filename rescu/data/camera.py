"""Pinhole camera and plane geometry of the synthetic benchmark.

Camera frame: x right, y down, z forward; pixels as in :mod:`rescu.types`. Plane points
``X = (u, v, 0)``; camera points ``X_c = R X + t``; ``K = [[f, 0, c_x], [0, f, c_y],
[0, 0, 1]]``; image point ``x ~ K X_c``; plane -> image homography ``H = K [r_1 r_2 t]``;
rows run along the plane axis ``d = (1, 0, 0)`` and their vanishing point is
``v = K R d`` (homogeneous, unit norm, ``w = 0`` for frontal planes).
"""

from __future__ import annotations

import math

import numpy as np


def camera_matrix(f: float, cx: float, cy: float) -> np.ndarray:
    """Pinhole intrinsics ``K`` (3, 3) float: focal ``f`` and principal point, pixels."""
    if not f > 0:
        raise ValueError(f"f must be > 0 pixels, got {f!r}")
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def rotation_matrix(axis: np.ndarray | tuple[float, float, float], angle: float
                    ) -> np.ndarray:
    """Rotation (3, 3) by ``angle`` radians about ``axis`` (3,) (Rodrigues)."""
    a = np.asarray(axis, float)
    if a.shape != (3,) or not np.linalg.norm(a) > 0:
        raise ValueError(f"axis must be a non-zero (3,) vector, got {axis!r}")
    a = a / np.linalg.norm(a)
    kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def _check_krt(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, ...]:
    K, R, t = np.asarray(K, float), np.asarray(R, float), np.asarray(t, float).reshape(-1)
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {K.shape}")
    if R.shape != (3, 3):
        raise ValueError(f"R must have shape (3, 3), got {R.shape}")
    if t.shape != (3,):
        raise ValueError(f"t must have shape (3,), got {t.shape}")
    return K, R, t


def project_points(K: np.ndarray, R: np.ndarray, t: np.ndarray, pts3d: np.ndarray
                   ) -> np.ndarray:
    """Project 3D points to pixels: ``x ~ K (R X + t)``.

    Parameters
    ----------
    K : (3, 3) float
        Intrinsics, pixels.
    R : (3, 3) float
        Rotation plane (world) -> camera.
    t : (3,) float
        Translation, plane units in the camera frame.
    pts3d : (N, 3) float, or (N, 2) plane points ``(u, v)`` (taken with ``z = 0``)
        Points, plane units.

    Returns
    -------
    (N, 2) float
        Pixel coordinates (x right, y down). Raises ValueError if a point is not in front
        of the camera (depth <= 0).
    """
    K, R, t = _check_krt(K, R, t)
    p = np.asarray(pts3d, float)
    if p.ndim != 2 or p.shape[1] not in (2, 3):
        raise ValueError(f"pts3d must have shape (N, 3) or (N, 2), got {p.shape}")
    if p.shape[1] == 2:
        p = np.column_stack([p, np.zeros(len(p))])
    xc = p @ R.T + t
    if len(xc) and not np.all(xc[:, 2] > 0):
        raise ValueError("project_points: some points are behind the camera (depth <= 0)")
    xh = xc @ K.T
    return xh[:, :2] / xh[:, 2:3]


def plane_homography(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Homography (3, 3) from plane points ``(u, v, 1)`` to pixels: ``H = K [r1 r2 t]``."""
    K, R, t = _check_krt(K, R, t)
    return K @ np.column_stack([R[:, 0], R[:, 1], t])


def _canonical_sign(v: np.ndarray) -> np.ndarray:
    """Sign convention for homogeneous points / directions: ``w > 0``; if ``w ~ 0`` the
    first non-zero coordinate is positive."""
    v = np.asarray(v, float)
    if abs(v[2]) > 1e-12:
        return v if v[2] > 0 else -v
    for c in v[:2]:
        if abs(c) > 1e-12:
            return v if c > 0 else -v
    return v


def row_vanishing_point(K: np.ndarray, R: np.ndarray,
                        d_plane: np.ndarray | tuple[float, float, float] = (1.0, 0.0, 0.0)
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Vanishing point of the plane direction ``d`` (3,): ``v = K R d``.

    Returns
    -------
    homogeneous : (3,) float
        Pixel point ``(x, y, w)``, unit norm, ``w >= 0`` (``w = 0``: at infinity).
    direction : (3,) float
        Unit 3D direction ``R d`` in the camera frame, with the sign matching
        ``homogeneous``.
    """
    K, R, _ = _check_krt(K, R, np.zeros(3))
    d = np.asarray(d_plane, float).reshape(-1)
    if d.shape != (3,) or not np.linalg.norm(d) > 0:
        raise ValueError(f"d_plane must be a non-zero (3,) vector, got {d_plane!r}")
    direc = R @ (d / np.linalg.norm(d))
    v = K @ direc
    v = v / np.linalg.norm(v)
    s = _canonical_sign(v)
    if not np.array_equal(s, v):
        direc = -direc
    return s, direc
