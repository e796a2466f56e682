"""Two-view relative pose from correspondences, robust to small baselines.

``cv2.recoverPose``'s cheirality test ignores points farther than 50 baseline lengths, so with
the small baselines of adjacent video frames (2 cm at 2 m is 100 baselines) it counts almost
no points and may return any of the four decompositions of E, including the 180-degree
"twisted pair". We decompose E ourselves and pick the solution that puts most points in front
of both cameras, with no distance limit.
"""

from __future__ import annotations

import cv2
import numpy as np


def triangulate_depths(pa: np.ndarray, pb: np.ndarray, K: np.ndarray, R: np.ndarray,
                       t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint triangulation. pa, pb (N, 2) px; x_b = R x_a + t. Returns depths (za, zb) (N,)."""
    Kinv = np.linalg.inv(K)
    ra = np.concatenate([pa, np.ones((len(pa), 1))], 1) @ Kinv.T
    rb_b = np.concatenate([pb, np.ones((len(pb), 1))], 1) @ Kinv.T
    rb = rb_b @ R  # rays of b expressed in a: R^T r
    cb = -R.T @ np.asarray(t, np.float64).ravel()
    a11 = np.sum(ra * ra, 1)
    a12 = -np.sum(ra * rb, 1)
    a22 = np.sum(rb * rb, 1)
    b1 = ra @ cb
    b2 = -(rb @ cb)
    det = a11 * a22 - a12 * a12
    det = np.where(np.abs(det) < 1e-15, np.nan, det)
    za = (b1 * a22 - a12 * b2) / det
    zb_a = (a11 * b2 - a12 * b1) / det  # scale of rb in a's frame: depth along b's ray
    return za, zb_a


def pose_from_essential(E: np.ndarray, pa: np.ndarray, pb: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(R, t unit, number of points in front) with x_b = R x_a + t; pa, pb (N, 2) inliers."""
    R1, R2, t = cv2.decomposeEssentialMat(E)
    best = (np.eye(3), np.zeros(3), -1)
    for R in (R1, R2):
        for s in (1.0, -1.0):
            tt = s * t.ravel()
            za, zb = triangulate_depths(pa, pb, K, R, tt)
            n = int(np.sum((za > 0) & (zb > 0)))
            if n > best[2]:
                best = (R, tt, n)
    return best


def relative_pose(pa: np.ndarray, pb: np.ndarray, K: np.ndarray, threshold: float = 1.0,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Essential-matrix RANSAC + cheirality: (R, t unit, inlier mask) or None."""
    if len(pa) < 8:
        return None
    cv2.setRNGSeed(seed)
    E, inl = cv2.findEssentialMat(pa, pb, K, method=cv2.RANSAC, prob=0.999, threshold=threshold)
    if E is None or E.shape != (3, 3) or inl is None:
        return None
    m = inl.ravel().astype(bool)
    R, t, n = pose_from_essential(E, pa[m], pb[m], K)
    if n <= 0:
        return None
    return R, t, m
