"""SE(3) of numpy arrays: exponential, logarithm and the logarithm's derivative, in gtsam's
conventions (the bundle adjustment's solver reproduces gtsam's Pose3 factors).

Twist order everywhere in gcvd-flow (here and ``stages.geometry.torch_ops``): xi = (omega, v),
rotation first (rad, axis-angle), then translation (gtsam's Pose3 tangent order; the same order
as ``torch_ops.pose_from_rt``'s (r, t)). Poses are (N, 4, 4) float64; ``se3_exp(xi)`` is the
pose [[exp(omega^), V(omega) v], [0, 1]].
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def hat(w: np.ndarray) -> np.ndarray:
    """(N, 3) -> (N, 3, 3) cross-product matrices."""
    z = np.zeros(len(w))
    return np.stack([z, -w[:, 2], w[:, 1], w[:, 2], z, -w[:, 0], -w[:, 1], w[:, 0], z], -1).reshape(-1, 3, 3)


def v_coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sin(t)/t, (1 - cos t)/t^2, (t - sin t)/t^3 with their series below 1e-4 rad (no 0/0)."""
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1 - theta**2 / 6, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(t)) / t**2)
    c = np.where(small, 1 / 6 - theta**2 / 120, (t - np.sin(t)) / t**3)
    return a, b, c


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """gtsam's Pose3.Expmap: xi (N, 6) = (omega rad, v) -> (N, 4, 4); R = exp(omega^),
    t = V(omega) v with V = I + (1 - cos t)/t^2 W + (t - sin t)/t^3 W^2."""
    w, v = xi[:, :3], xi[:, 3:]
    W = hat(w)
    _, b, c = v_coefficients(np.linalg.norm(w, axis=1))
    V = np.eye(3) + b[:, None, None] * W + c[:, None, None] * (W @ W)
    T = np.tile(np.eye(4), (len(xi), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(w).as_matrix()
    T[:, :3, 3] = np.einsum("nij,nj->ni", V, v)
    return T


def se3_log(T: np.ndarray) -> np.ndarray:
    """gtsam's Pose3.Logmap, the inverse of :func:`se3_exp`: (N, 4, 4) -> (N, 6) (omega, v)."""
    w = Rotation.from_matrix(T[:, :3, :3]).as_rotvec()
    theta = np.linalg.norm(w, axis=1)
    a, b, _ = v_coefficients(theta)
    # V^-1 = I - W/2 + (1 - a / (2 b)) / t^2 W^2; the coefficient tends to 1/12 at t -> 0
    small = theta < 1e-4
    t = np.where(small, 1.0, theta)
    e = np.where(small, 1 / 12 + theta**2 / 720, (1 - a / (2 * b)) / t**2)
    W = hat(w)
    Vinv = np.eye(3) - 0.5 * W + e[:, None, None] * (W @ W)
    return np.concatenate([w, np.einsum("nij,nj->ni", Vinv, T[:, :3, 3])], 1)


def se3_dlog(xi: np.ndarray, terms: int = 40) -> np.ndarray:
    """(N, 6) -> (N, 6, 6): d Log(Exp(xi) Exp(d)) / d d at d = 0, the inverse of the right Jacobian
    J_r(xi) = sum_n (-ad_xi)^n / (n + 1)!, ad_xi = [[W, 0], [V, W]] (gtsam's adjointMap). The
    series is entire; 40 terms are exact to double precision for |omega| <= pi and the translations
    a prior residual has (a closed form of the SE(3) Jacobian would be longer and easier to get wrong)."""
    n = len(xi)
    ad = np.zeros((n, 6, 6))
    ad[:, :3, :3] = ad[:, 3:, 3:] = hat(xi[:, :3])
    ad[:, 3:, :3] = hat(xi[:, 3:])
    J = np.tile(np.eye(6), (n, 1, 1))
    for k in range(terms, 0, -1):  # Horner: I + (-ad)/2 (I + (-ad)/3 (I + ...))
        J = np.eye(6) - (ad @ J) / (k + 1)
    return np.linalg.inv(J)


def loop_disagreement_deg(T_w_a: np.ndarray, T_w_b: np.ndarray, T_b_a: np.ndarray) -> float:
    """Rotation angle (degrees) between a measured relative pose T_b_a = inv(T_w_b) @ T_w_a (a loop
    edge, (4, 4)) and the one the camera-to-world poses T_w_a, T_w_b (4, 4 float64) imply."""
    T_a_b = np.linalg.inv(np.asarray(T_b_a, np.float64))
    T_a_b_odo = np.linalg.inv(T_w_a) @ T_w_b
    dR = T_a_b_odo[:3, :3].T @ T_a_b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
