"""Edge-aware, confidence-weighted smoothing of the final depth (``depth_consensus.smooth_lambda``).

Why: on real footage the depth of the unconfident pixels (texture-less walls, cabinet fronts, a
grey wardrobe: no flow triangulates them) is the optimised depth densified from sparse
measurements, blotchy at the scale of tens of pixels (+-10-30 % patches on one flat surface);
the consensus splat fixes what other views see confidently and leaves the rest. Averaging log
depth along the image -- weighted by confidence, stopped at colour edges -- replaces the
blotches by what the surface's confident pixels and its own depth say on average: a wall's
depth follows the confident pixels that share its colour, a receding floor keeps its ramp
(a symmetric average leaves a linear profile in place).

The solver is the fast global smoother (Min et al., "Fast Global Image Smoothing Based on
Weighted Least Squares", TIP 2014) in its normalised form: FGS(w x) / FGS(w), each FGS pass a
1-D weighted-least-squares solve along every row, then every column (tridiagonal: one LAPACK
banded solve over the whole image, both right-hand sides at once), ``iters`` passes with the
smoothness lambda falling as 1.5 * 4^(T - t - 1) / (4^T - 1). Neighbour weights are
exp(-|I_p - I_q|^2 / sigma^2) on the RGB image in [0, 1] (a colour edge with little grey-level
contrast stops it too: the synthetic clips' coloured walls). ~15 ms per 256x192 frame.

Through the pipeline against main at ef8095f (docs/log/2026-11-28-depth4.md): AbsRel HoloLens
0.1205 -> 0.1058, ICL 0.0413 -> 0.0394, synthetic loop 0.0344 -> 0.0239, 300-frame walk 0.0459 ->
0.0359; confident AbsRel equal or lower (walk +0.1 %); poses untouched.

Pure numpy / SciPy, deterministic (LAPACK's banded LU, no threads involved in the result).
Shapes: depth float32 (H, W) (0 = invalid), confidence (H, W) in [0, 1], image (H, W, 3) uint8
or float in 0..255.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_banded

CONFIDENCE_POWER = 2  # data weight confidence^2 + floor, as the consensus weighs its views
KEEP_POWER = 2.0


def edge_weights(image: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Neighbour affinities exp(-|I_p - I_q|^2 / sigma^2) of an (H, W) or (H, W, C) image in
    [0, 1]: (H, W - 1) between horizontal neighbours, (H - 1, W) between vertical ones."""
    img = np.asarray(image, np.float64)
    if img.ndim == 2:
        img = img[..., None]
    inv = 1.0 / (float(sigma) ** 2)
    ax = np.exp(-_channel_sum(np.square(img[:, 1:] - img[:, :-1])) * inv)
    ay = np.exp(-_channel_sum(np.square(img[1:] - img[:-1])) * inv)
    return ax, ay


def _channel_sum(x: np.ndarray) -> np.ndarray:
    """x.sum(-1), the same bits for up to 3 channels (numpy adds them in this order), without the
    slow reduction over a short last axis."""
    if x.shape[-1] > 3:
        return x.sum(-1)
    c = np.moveaxis(x, -1, 0)
    out = np.ascontiguousarray(c[0])
    for k in range(1, x.shape[-1]):
        out += c[k]
    return out


def _solve_rows(rhs: np.ndarray, coupling: np.ndarray) -> np.ndarray:
    """x minimising |x - rhs|^2 + sum coupling (x_p - x_{p+1})^2 along every row, for each of
    rhs's last-axis channels: rhs (H, W, C), coupling (H, W - 1) >= 0. The rows are chained into
    one tridiagonal system (zero coupling across row ends) solved by one banded LU."""
    h, w, ch = rhs.shape
    grid = np.zeros((h, w))
    grid[:, :-1] = coupling
    off = grid.ravel()
    ab = np.empty((3, h * w))
    ab[1] = 1.0 + off
    ab[1, 1:] += off[:-1]
    ab[0, 0] = 0.0
    ab[0, 1:] = -off[:-1]
    ab[2, :-1] = -off[:-1]
    ab[2, -1] = 0.0
    x = solve_banded((1, 1), ab, rhs.reshape(h * w, ch), overwrite_ab=True, check_finite=False)
    return x.reshape(h, w, ch)


def fast_global_smooth(values: np.ndarray, weights: np.ndarray, image: np.ndarray, lam: float, sigma: float,
                       iters: int = 3) -> np.ndarray:
    """The weighted edge-aware average of ``values`` (H, W): FGS(weights * values) / FGS(weights)
    over ``image`` (H, W[, C]) in [0, 1] (module docstring). Where no weight reaches a pixel the
    result is 0 there."""
    ax, ay = edge_weights(image, sigma)
    wgt = np.asarray(weights, np.float64)
    stack = np.stack([np.asarray(values, np.float64) * wgt, wgt], -1)
    for t in range(iters):
        lam_t = 1.5 * 4.0 ** (iters - t - 1) / (4.0 ** iters - 1.0) * lam
        stack = _solve_rows(stack, lam_t * ax)
        stack = _solve_rows(stack.transpose(1, 0, 2), lam_t * ay.T).transpose(1, 0, 2)
    den = stack[..., 1]
    return np.where(den > 1e-12, stack[..., 0] / np.maximum(den, 1e-12), 0.0)


def smooth_depth(depth: np.ndarray, confidence: np.ndarray, image: np.ndarray, lam: float, sigma: float,
                 keep: float, static: np.ndarray | None = None, floor: float = 0.01, iters: int = 3) -> np.ndarray:
    """Depth float32 (H, W) with its log averaged edge-aware over the image, each valid pixel
    weighted confidence^2 + ``floor``; a pixel keeps (confidence / ``keep``)^2 (at most all) of
    its own log depth, so pixels at least ``keep`` confident are unchanged. Invalid (0) pixels
    stay 0; ``lam`` <= 0 returns the depth unchanged. ``static`` (H, W), 1 = take part (the
    stage passes the user's --masks keep): the other pixels keep their depth and lend none."""
    depth = np.asarray(depth, np.float32)
    valid = depth > 0
    if lam <= 0 or not valid.any():
        return depth
    conf = np.clip(np.asarray(confidence, np.float64), 0.0, 1.0)
    log_d = np.log(np.where(valid, depth, 1.0).astype(np.float64))
    use = valid if static is None else valid & (np.asarray(static) > 0)
    wgt = np.where(use, conf ** CONFIDENCE_POWER + floor, 0.0)
    img = np.asarray(image, np.float64) / 255.0
    smooth = fast_global_smooth(log_d, wgt, img, lam, sigma, iters)
    alpha = np.clip(conf / max(keep, 1e-6), 0.0, 1.0) ** KEEP_POWER if keep > 0 else np.zeros_like(conf)
    out = alpha * log_d + (1.0 - alpha) * smooth
    out = np.where(use, np.exp(out), depth)
    return np.where(valid, out, 0.0).astype(np.float32)
