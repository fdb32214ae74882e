"""Which points of a new scan fall where the submap's keyframes have looked.

A likelihood grid cannot tell "no surface here" from "never seen": a scan point on a surface the submap never saw
(the inside face of a door jamb just passed, a wall behind a pillar) is pulled to the nearest surface the submap
holds. Along a corridor whose submap was seen from behind, those pulls all point the same way and bias the match
along the corridor by a centimetre or so per match, which accumulates into drift. Such points are left out of the
match.

Each keyframe's view is a range profile around its laser origin o: per bearing bin b (``n_bins`` over 360°), the
longest hit range R(b), widened to the neighbouring bins. A world point q is *seen* by that keyframe when its bin
held a hit and ‖q − o‖ ≤ R(b(q)) + ``margin_m`` (the ray reached at least that far), b(q) = ⌊(atan2(q − o) + π) /
2π · n_bins⌋.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _bins(delta_xy: np.ndarray, n_bins: int) -> np.ndarray:
    bearing = np.arctan2(delta_xy[..., 1], delta_xy[..., 0])
    bins: np.ndarray = (np.floor((bearing + np.pi) / (2.0 * np.pi) * n_bins).astype(np.intp)) % n_bins
    return bins


@dataclass(frozen=True)
class ViewProfiles:
    """Laser origins (K, 2) in the world and their range profiles (K, n_bins), −1 where a bin held no hit."""

    origins_xy_m: np.ndarray
    max_range_m: np.ndarray

    @classmethod
    def from_scans(cls, origins_xy_m: list[np.ndarray], hits_xy_m: list[np.ndarray], n_bins: int = 720, *,
                   shortest_ray: bool = False) -> ViewProfiles:
        """Profiles of scans given as world-frame laser origins (2,) and hit points (N, 2); ``shortest_ray``: the
        shortest hit range over a bin and its neighbours instead of the longest (a jamb hides the recess behind)."""
        if len(origins_xy_m) != len(hits_xy_m):
            raise ValueError(f"{len(origins_xy_m)} origins for {len(hits_xy_m)} scans")
        if n_bins < 8:
            raise ValueError(f"n_bins must be at least 8 (got {n_bins})")
        reduce, empty = (np.minimum, np.inf) if shortest_ray else (np.maximum, -1.0)
        profiles = np.full((len(hits_xy_m), n_bins), empty)
        for k, (origin, hits) in enumerate(zip(origins_xy_m, hits_xy_m, strict=True)):
            if len(hits) == 0:
                continue
            delta = np.asarray(hits, float) - np.asarray(origin, float)
            reduce.at(profiles[k], _bins(delta, n_bins), np.hypot(delta[:, 0], delta[:, 1]))
        widened = reduce(profiles, reduce(np.roll(profiles, 1, axis=1), np.roll(profiles, -1, axis=1)))
        widened[np.isinf(widened)] = -1.0  # no hit in the bin or its neighbours
        return cls(np.asarray(origins_xy_m, float).reshape(-1, 2), widened)

    def seen(self, points_xy_m: np.ndarray, margin_m: float) -> np.ndarray:
        """Mask (N,) of world points that at least one profile's rays reached (within ``margin_m``)."""
        points = np.asarray(points_xy_m, float)
        if len(self.origins_xy_m) == 0:
            return np.zeros(len(points), bool)
        n_bins = self.max_range_m.shape[1]
        delta = points[None, :, :] - self.origins_xy_m[:, None, :]
        reach = np.take_along_axis(self.max_range_m, _bins(delta, n_bins), axis=1)
        return np.asarray(((reach >= 0.0) & (np.hypot(delta[..., 0], delta[..., 1]) <= reach + margin_m)).any(axis=0))
