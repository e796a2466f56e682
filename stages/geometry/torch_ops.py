"""Differentiable camera geometry in torch (SE(3), back-projection, projection, point sampling).

Conventions (docs/contributing.md): pixel (u, v) = (column, row), the centre of the top-left pixel
is (0, 0); poses are T_w_c (camera-to-world 4x4, OpenCV axes); depth is z-depth. A relative
pose ``T_b_a`` (4, 4) maps camera-a coordinates to camera-b coordinates:
``T_b_a = inv(T_w_b) @ T_w_a`` (``relative_pose(T_w_a, T_w_b)``).

The 6-vector pose parameterisation used by the optimiser is ``(r, t)``: axis-angle rotation
``r`` (rad) and translation ``t`` (scene units), ``T = [[R(r), t], [0, 1]]``. Proper SE(3)
``se3_exp`` / ``se3_log`` are provided as well, with the twist in the order used everywhere in
gcvd-flow: ``(w, v)`` = (rotation rad, then translation), as ``stages.geometry.se3`` (numpy) and
gtsam's Pose3, and as ``(r, t)`` above.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = [
    "so3_exp",
    "so3_log",
    "se3_exp",
    "se3_log",
    "pose_from_rt",
    "rt_from_pose",
    "relative_pose",
    "pixel_rays",
    "backproject",
    "transform",
    "project",
    "rigid_flow",
    "sample_bilinear",
    "sample_points",
    "inside_image",
    "sample_frames",
    "footprint_kept",
    "gather_pixels",
]

_EPS = 1e-6


def _skew(w: torch.Tensor) -> torch.Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices."""
    o = torch.zeros_like(w[..., 0])
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2
    )


def _theta_terms(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """theta^2, A = sin(t)/t, B = (1-cos t)/t^2 with Taylor series near 0 (gradient-safe at 0)."""
    th2 = (w * w).sum(-1)
    small = th2 < 1e-6
    # evaluate the closed form on a safe value so that the unused branch never produces NaN grads
    th2s = torch.where(small, torch.ones_like(th2), th2)
    th = th2s.sqrt()
    a = torch.where(small, 1 - th2 / 6 + th2 * th2 / 120, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24 + th2 * th2 / 720, (1 - torch.cos(th)) / th2s)
    return th2, a, b


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: axis-angle (..., 3) [rad] -> rotation matrices (..., 3, 3)."""
    _, a, b = _theta_terms(w)
    W = _skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(W.shape)
    return eye + a[..., None, None] * W + b[..., None, None] * (W @ W)


def so3_log(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (..., 3, 3) -> axis-angle (..., 3) [rad], valid for angles < pi - 1e-3."""
    v = torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    # atan2(sin, cos) is accurate at small angles, unlike acos of a trace close to 3
    sin2 = (v * v).sum(-1)  # (2 sin th)^2
    cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2
    th = torch.atan2(0.5 * sin2.clamp(min=1e-30).sqrt(), cos)
    small = th < 1e-4
    ths = torch.where(small, torch.ones_like(th), th)
    scale = torch.where(small, 0.5 + th * th / 12, ths / (2 * torch.sin(ths)))
    return v * scale[..., None]


def _left_jacobian(w: torch.Tensor) -> torch.Tensor:
    """SO(3) left Jacobian V (..., 3, 3) used by the SE(3) exponential."""
    th2, _, b = _theta_terms(w)
    small = th2 < 1e-6
    th2s = torch.where(small, torch.ones_like(th2), th2)
    th = th2s.sqrt()
    c = torch.where(small, 1.0 / 6 - th2 / 120, (th - torch.sin(th)) / (th2s * th))
    W = _skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand(W.shape)
    return eye + b[..., None, None] * W + c[..., None, None] * (W @ W)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """SE(3) exponential: twist (..., 6) = (w, v) (rotation rad first, as ``stages.geometry.se3`` and
    gtsam) -> (..., 4, 4)."""
    w, v = xi[..., :3], xi[..., 3:]
    R = so3_exp(w)
    t = (_left_jacobian(w) @ v[..., None])[..., 0]
    return _assemble(R, t)


def se3_log(T: torch.Tensor) -> torch.Tensor:
    """SE(3) logarithm: (..., 4, 4) -> twist (..., 6) = (w, v), the inverse of :func:`se3_exp`."""
    w = so3_log(T[..., :3, :3])
    v = torch.linalg.solve(_left_jacobian(w), T[..., :3, 3:4])[..., 0]
    return torch.cat([w, v], -1)


def _assemble(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    bottom = torch.zeros(R.shape[:-2] + (1, 4), dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat([torch.cat([R, t[..., None]], -1), bottom], -2)


def pose_from_rt(rt: torch.Tensor) -> torch.Tensor:
    """(..., 6) = (axis-angle r [rad], translation t) -> (..., 4, 4) = [[R(r), t], [0, 1]]."""
    return _assemble(so3_exp(rt[..., :3]), rt[..., 3:])


def rt_from_pose(T: torch.Tensor) -> torch.Tensor:
    """Inverse of ``pose_from_rt``: (..., 4, 4) -> (..., 6)."""
    return torch.cat([so3_log(T[..., :3, :3]), T[..., :3, 3]], -1)


def relative_pose(T_w_a: torch.Tensor, T_w_b: torch.Tensor) -> torch.Tensor:
    """T_b_a = inv(T_w_b) @ T_w_a (..., 4, 4): maps camera-a coordinates to camera-b coordinates,
    for camera-to-world poses T_w_a, T_w_b (..., 4, 4); rigid inverse (no solve)."""
    Rb, tb = T_w_b[..., :3, :3], T_w_b[..., :3, 3:4]
    Rbt = Rb.transpose(-1, -2)
    Ra, ta = T_w_a[..., :3, :3], T_w_a[..., :3, 3:4]
    return _assemble(Rbt @ Ra, (Rbt @ (ta - tb))[..., 0])


def pixel_rays(h: int, w: int, K: torch.Tensor) -> torch.Tensor:
    """(H*W, 3) rays K^-1 [u, v, 1] (z = 1), row-major pixel order."""
    v, u = torch.meshgrid(
        torch.arange(h, dtype=K.dtype), torch.arange(w, dtype=K.dtype), indexing="ij"
    )
    x = (u.reshape(-1) - K[0, 2]) / K[0, 0]
    y = (v.reshape(-1) - K[1, 2]) / K[1, 1]
    return torch.stack([x, y, torch.ones_like(x)], -1)


def backproject(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Depth (B, H, W) z-depth + K (3, 3) -> camera points (B, H*W, 3)."""
    b, h, w = depth.shape
    return pixel_rays(h, w, K.to(depth.dtype))[None] * depth.reshape(b, -1, 1)


def transform(T: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """Apply (B, 4, 4) to points (B, M, 3)."""
    return X @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]


def project(X: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera points (..., 3) -> (pixels (..., 2), z (...)); z is clamped to 1e-6 for the division."""
    x, y, z = X.unbind(-1)  # one backward (a stack) instead of three zero-filled selects
    zc = z.clamp(min=_EPS)
    u = K[0, 0] * x / zc + K[0, 2]
    v = K[1, 1] * y / zc + K[1, 2]
    return torch.stack([u, v], -1), z


def rigid_flow(depth_a: torch.Tensor, K: torch.Tensor, T_b_a: torch.Tensor) -> torch.Tensor:
    """Flow a -> b (B, H, W, 2) px induced on a static scene by depth_a (B, H, W) and the relative
    pose T_b_a (B, 4, 4) (camera a -> camera b coordinates)."""
    b, h, w = depth_a.shape
    K = K.to(depth_a.dtype)
    X = transform(T_b_a.to(depth_a.dtype), backproject(depth_a, K))
    uv, _ = project(X, K)
    v, u = torch.meshgrid(
        torch.arange(h, dtype=depth_a.dtype), torch.arange(w, dtype=depth_a.dtype), indexing="ij"
    )
    grid = torch.stack([u, v], -1).reshape(1, -1, 2)
    return (uv - grid).reshape(b, h, w, 2)


def sample_bilinear(img: torch.Tensor, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinearly sample img (B, C, H, W) at pixel points uv (B, M, 2) -> ((B, M, C), inside (B, M)).

    Uses grid_sample on a (B, 1, M) point grid, so the cost is O(M), not O(H*W)
    (docs/design.md, "Lessons from the prototype").
    ``inside`` is True where the point lies within the pixel-centre box [0, W-1] x [0, H-1].
    """
    h, w = img.shape[-2:]
    return sample_points(img, uv), inside_image(uv, h, w)


def sample_points(img: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """``sample_bilinear``'s samples (B, M, C) without ``inside``. The grid is uv scaled by one
    (2,) tensor: the same bits as scaling its two columns apart, without their selects' and the
    stack's backward (each select's backward fills a zero tensor of uv's size)."""
    h, w = img.shape[-2:]
    scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], dtype=uv.dtype)
    grid = (uv * scale - 1)[:, None]
    out = F.grid_sample(img, grid.to(img.dtype), mode="bilinear", padding_mode="border", align_corners=True)
    return out[:, :, 0].transpose(1, 2)


def inside_image(uv: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Whether pixel points uv (..., 2) lie within the pixel-centre box [0, w-1] x [0, h-1] -> (...) bool."""
    return (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)


def sample_frames(field: torch.Tensor, frame: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinearly sample frame ``frame[p]`` of a stack field (n, H, W) at pixel points uv (P, M, 2)
    -> (P, M), with ``sample_bilinear``'s conventions (border clamp, pixel-centre grid).

    The same values as ``sample_bilinear(field[frame][:, None], uv)`` without building the (P, H, W)
    stack ``field[frame]``: four gathers from the flat field, so the cost and the backward
    (a scatter into n * H * W values instead of P * H * W) are O(P * M), not O(P * H * W)."""
    n, h, w = field.shape
    x = uv[..., 0].clamp(0, w - 1)
    y = uv[..., 1].clamp(0, h - 1)
    x0 = x.detach().floor().clamp(max=max(w - 2, 0))
    y0 = y.detach().floor().clamp(max=max(h - 2, 0))
    ax, ay = x - x0, y - y0
    i00 = (frame[:, None] * (h * w) + y0.long() * w + x0.long()).reshape(-1)
    dx, dy = min(1, w - 1), min(1, h - 1) * w
    flat = field.reshape(-1)
    # gather rather than flat[i]: the same values, a cheaper backward (scatter-add vs index_put)
    f00, f01 = flat.gather(0, i00).view_as(x), flat.gather(0, i00 + dx).view_as(x)
    f10, f11 = flat.gather(0, i00 + dy).view_as(x), flat.gather(0, i00 + dx + dy).view_as(x)
    top = f00 + (f01 - f00) * ax
    bottom = f10 + (f11 - f10) * ax
    return top + (bottom - top) * ay


def footprint_kept(keep: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Whether bilinear samples at pixel points uv (P, M, 2) of frames keep (P, H, W) bool mix only
    kept pixels -> (P, M) bool: the four pixels floor(u) + {0, 1}, floor(v) + {0, 1} (clamped to
    the image, as the samplers clamp) are all kept. Counts the second pixel even at a weight of
    0: grid_sample's coordinate round trip may give it a weight of 1e-7."""
    p, h, w = keep.shape
    uv = torch.nan_to_num(uv.detach(), nan=0.0, posinf=1e9, neginf=-1e9)
    x0 = uv[..., 0].clamp(0, w - 1).floor().long()
    y0 = uv[..., 1].clamp(0, h - 1).floor().long()
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    flat = keep.reshape(p, h * w)
    ok = flat.gather(1, (y0 * w + x0).reshape(p, -1)) & flat.gather(1, (y0 * w + x1).reshape(p, -1))
    ok &= flat.gather(1, (y1 * w + x0).reshape(p, -1)) & flat.gather(1, (y1 * w + x1).reshape(p, -1))
    return ok.reshape(uv.shape[:-1])


def gather_pixels(img: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """img (B, C, H, W), flat integer pixel indices idx (B, M) -> (B, M, C) (exact, no interpolation)."""
    b, c, h, w = img.shape
    flat = img.reshape(b, c, h * w)
    return flat.gather(2, idx[:, None, :].expand(b, c, idx.shape[1])).transpose(1, 2)
