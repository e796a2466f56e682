"""The shared two-view triangulation (stages.geometry.two_view): the one-pass depth + angle that
the priors and depth fusion call is the previous two-function computation, bit for bit."""

from __future__ import annotations

import cv2
import numpy as np

from gcvd_flow.stages.geometry.two_view import triangulate_depths, triangulate_with_angles


def _former_angles_deg(p, q, K, R):
    """The angle as priors and depth fusion computed it before they shared the triangulation's rays."""
    Kinv = np.linalg.inv(K)
    ra = np.concatenate([p, np.ones((len(p), 1))], 1) @ Kinv.T
    rb = (np.concatenate([q, np.ones((len(q), 1))], 1) @ Kinv.T) @ R
    c = np.sum(ra * rb, 1) / (np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def test_triangulation_with_angles_is_the_two_functions_bit_for_bit() -> None:
    rng = np.random.default_rng(3)
    K = np.array([[210.0, 0, 127.5], [0, 211.0, 95.5], [0, 0, 1]])
    for n in (1, 7, 1000, 49_153):
        p = rng.uniform(0, 256, (n, 2))
        q = p + rng.normal(0, 3, (n, 2))
        q[: min(n, 5) // 2] = p[: min(n, 5) // 2]  # parallel rays: NaN depth, zero angle
        R = cv2.Rodrigues(rng.normal(0, 0.05, 3))[0]
        t = rng.normal(0, 0.1, 3)
        z, ang = triangulate_with_angles(p, q, K, R, t)
        z0, _ = triangulate_depths(p, q, K, R, t)
        assert z.tobytes() == z0.tobytes()
        assert ang.tobytes() == _former_angles_deg(p, q, K, R).tobytes()
        if n > 10:
            assert np.isfinite(z).sum() > 0.8 * n
