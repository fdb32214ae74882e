"""SE(2) helpers on poses ``(x, y, theta)`` in metres and radians (arrays of shape (3,) or (N, 3))."""

from __future__ import annotations

import numpy as np


def wrap_angle(theta: np.ndarray | float) -> np.ndarray | float:
    """Angle folded into [-pi, pi)."""
    return (np.asarray(theta) + np.pi) % (2.0 * np.pi) - np.pi


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a ⊕ b: pose b expressed in frame a, returned in a's parent frame."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: np.ndarray) -> np.ndarray:
    """⊖a, so that a ⊕ (⊖a) = 0."""
    a = np.asarray(a, float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(⊖a) ⊕ b: pose b seen from frame a."""
    return compose(inverse(a), b)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 2) given in frame ``pose`` expressed in the parent frame: R(theta) p + t."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    out = np.empty_like(points, dtype=float)
    out[:, 0] = c * points[:, 0] - s * points[:, 1] + pose[0]
    out[:, 1] = s * points[:, 0] + c * points[:, 1] + pose[1]
    return out


def interpolate(stamps_s: np.ndarray, poses: np.ndarray, at_s: np.ndarray) -> np.ndarray:
    """Poses linearly interpolated (angles along the shortest arc) at ``at_s``; clamped at the ends."""
    stamps_s = np.asarray(stamps_s, float)
    at_s = np.atleast_1d(np.asarray(at_s, float))
    unwrapped = np.unwrap(poses[:, 2])
    x = np.interp(at_s, stamps_s, poses[:, 0])
    y = np.interp(at_s, stamps_s, poses[:, 1])
    th = np.interp(at_s, stamps_s, unwrapped)
    return np.stack([x, y, wrap_angle(th)], axis=-1)
