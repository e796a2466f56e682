"""SIFT features and ratio-test matching (stages.sfm): the front end of the focal
self-calibration and of loop verification. Keypoints honour the user's masks (--masks): a keypoint
on, next to, or whose descriptor's support reaches a masked pixel is dropped before the strongest
are kept. Positions are pixels (x, y) at the frames' working resolution."""

from __future__ import annotations

import cv2
import numpy as np

from gcvd_flow.stages.geometry.image import to_gray

SiftFeatures = tuple[np.ndarray, np.ndarray | None]  # keypoint positions (K, 2) px, descriptors (K, 128)


# The user's mask (--masks) grows by this many px before keypoints are kept off it: a SIFT keypoint's
# rounded location and the centre of its descriptor's support stay off the masked pixels.
MASK_DILATE_PX = 4


# ... and a keypoint whose blob (MASK_SUPPORT x its SIFT size, the diameter OpenCV reports) reaches a
# masked pixel is dropped too: a large-scale keypoint next to the mask describes the masked content
# (an image-fixed patch's edge then makes an image-fixed track).
MASK_SUPPORT = 1.0


def usable(keep: np.ndarray, dilate_px: int = MASK_DILATE_PX) -> np.ndarray:
    """The user's kept mask (H, W), 1 = not masked -> uint8 (H, W), 1 = a keypoint may sit here:
    kept and more than ``dilate_px`` px (Chebyshev) from any masked pixel, so that neither a
    keypoint's rounded location nor the core of its descriptor's support is on the mask."""
    k = (np.asarray(keep) > 0).astype(np.uint8)
    return cv2.erode(k, np.ones((2 * dilate_px + 1,) * 2, np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1)


def sift_features(img: np.ndarray, n_features: int, keep: np.ndarray | None = None, contrast: float = 0.02
                  ) -> SiftFeatures:
    """SIFT keypoints (M, 2) px and descriptors (M, 128) of an image: the ``n_features`` strongest
    (0: all), detected at OpenCV's ``contrast`` threshold.
    With ``keep`` (the user's kept mask (H, W), 1 = not masked) the strongest among those not
    on or within MASK_DILATE_PX of a masked pixel and whose blob (MASK_SUPPORT x size) reaches
    none: OpenCV keeps its n strongest *before* it applies a detection mask, so a textured masked
    area would otherwise take the budget; here the cap comes after the mask."""
    gray = to_gray(img)
    if keep is None:
        sift = cv2.SIFT_create(nfeatures=n_features, contrastThreshold=contrast)  # type: ignore[attr-defined]
        kp, des = sift.detectAndCompute(gray, None)
        return np.asarray([k.pt for k in kp], np.float64).reshape(-1, 2), des
    sift = cv2.SIFT_create(nfeatures=0, contrastThreshold=contrast)  # type: ignore[attr-defined]
    ok = usable(keep)
    kp = sift.detect(gray, ok)
    if kp:
        h, w = ok.shape
        pts = np.asarray([k.pt for k in kp], np.float64).reshape(-1, 2)
        xi = np.clip(np.round(pts[:, 0]).astype(np.int64), 0, w - 1)
        yi = np.clip(np.round(pts[:, 1]).astype(np.int64), 0, h - 1)
        # px from each pixel to the nearest masked one (L2; large where nothing is masked)
        dist = cv2.distanceTransform((np.asarray(keep) > 0).astype(np.uint8), cv2.DIST_L2, 5)
        size = np.asarray([k.size for k in kp], np.float64)
        sel = np.flatnonzero((ok[yi, xi] > 0) & (dist[yi, xi] > MASK_SUPPORT * size))
        order = sel[np.argsort(-np.asarray([kp[i].response for i in sel]), kind="stable")][:n_features]
        kp = [kp[i] for i in order]
    if not kp:
        return np.zeros((0, 2), np.float64), None
    kp, des = sift.compute(gray, kp)
    return np.asarray([k.pt for k in kp], np.float64).reshape(-1, 2), des


class UniqueRatioMatcher:
    """Ratio-test matches (Lowe's ``ratio``) of feature pairs, one per keypoint of b, each pair
    matched once (the calibrate stage's frame selection, pair geometry and tracks ask for the same
    pairs): {(id(desc a), id(desc b)): (ia, ib) keypoint indices}."""

    def __init__(self, ratio: float = 0.8):
        self.ratio = ratio
        self.cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, fa, fb) -> tuple[np.ndarray, np.ndarray]:
        (pa, da), (pb, db) = fa, fb
        if da is None or db is None or len(pa) < 8 or len(pb) < 8:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        key = (id(da), id(db))
        if key not in self.cache:
            knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
            # one match per keypoint of b (the first in a's order): duplicates bias the fit
            best: dict[int, int] = {}
            for m in knn:
                if len(m) == 2 and m[0].distance < self.ratio * m[1].distance and m[0].trainIdx not in best:
                    best[m[0].trainIdx] = m[0].queryIdx
            self.cache[key] = (np.asarray(list(best.values()), np.int64), np.asarray(list(best.keys()), np.int64))
        return self.cache[key]


def matched_points(fa, fb, knn: UniqueRatioMatcher) -> tuple[np.ndarray, np.ndarray]:
    """Matched pixel positions (x_a, x_b), (M, 2) each, of two frames' features."""
    ia, ib = knn(fa, fb)
    return fa[0][ia].reshape(-1, 2), fb[0][ib].reshape(-1, 2)


def ratio_matches(fa: SiftFeatures, fb: SiftFeatures, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Every ratio-test match (Lowe's ``ratio``) of two images' features, a keypoint of b possibly
    matched twice (loop verification's RANSAC sorts them): (pts_a (M, 2), pts_b (M, 2)) float64
    px, deterministic order."""
    (pos_a, des_a), (pos_b, des_b) = fa, fb
    if des_a is None or des_b is None or len(pos_a) < 2 or len(pos_b) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(des_a, des_b, k=2)
    pairs = [(m[0].queryIdx, m[0].trainIdx) for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    ia = np.asarray([q for q, _ in pairs], np.int64)
    ib = np.asarray([t for _, t in pairs], np.int64)
    return pos_a[ia].reshape(-1, 2), pos_b[ib].reshape(-1, 2)
