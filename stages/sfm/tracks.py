"""Feature tracks (stages.sfm): RANSAC-verified SIFT matches chained over nearby frames into
tracks {frame position: pixel (2,)}, and a spatially bucketed selection of them."""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

from gcvd_flow.stages.sfm.features import UniqueRatioMatcher

RANSAC_SEED = 1234


class UnionFind:
    def __init__(self):
        self.parent: dict[tuple[int, int], tuple[int, int]] = {}

    def find(self, x):
        self.parent.setdefault(x, x)
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def union(self, a, b):
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def verified_matches(fa, fb, ransac_px: float, min_inliers: int, knn: UniqueRatioMatcher
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """Keypoint indices (ia, ib) of a pair's ratio-test matches that a RANSAC F keeps."""
    ia, ib = knn(fa, fb)
    if len(ia) < min_inliers:
        return None
    cv2.setRNGSeed(RANSAC_SEED)
    F, inl = cv2.findFundamentalMat(fa[0][ia], fb[0][ib], cv2.FM_RANSAC, ransac_px, 0.999, 5000)
    if F is None or inl is None:
        return None
    keep = inl.ravel().astype(bool)
    return (ia[keep], ib[keep]) if keep.sum() >= min_inliers else None


def feature_tracks(feats: list, knn: UniqueRatioMatcher, ransac_px: float = 1.0, min_inliers: int = 20,
                   offsets: Sequence[int] = (1, 2, 3)) -> list[dict[int, np.ndarray]]:
    """Features of the sampled frames (positions (K, 2) px, descriptors) -> tracks: {frame position:
    pixel (2,)} seen in >= 3 frames, from RANSAC-verified matches chained over frame pairs; a track
    claiming two keypoints in one frame is dropped."""
    uf = UnionFind()
    for a in range(len(feats)):
        for off in offsets:
            b = a + off
            if b >= len(feats):
                break
            m = verified_matches(feats[a], feats[b], ransac_px, min_inliers, knn)
            if m is None:
                continue
            for i, j in zip(*m):
                uf.union((a, int(i)), (b, int(j)))
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for node in sorted(uf.parent):
        groups.setdefault(uf.find(node), []).append(node)
    tracks = []
    for nodes in groups.values():
        frames = [f for f, _ in nodes]
        if len(nodes) < 3 or len(set(frames)) != len(frames):
            continue
        tracks.append({f: feats[f][0][k] for f, k in nodes})
    return tracks


def select_tracks(tracks: list[dict[int, np.ndarray]], size: tuple[int, int], per_frame: int,
                  grid: tuple[int, int] = (8, 6)) -> list[dict[int, np.ndarray]]:
    """At most about ``per_frame`` tracks per frame, spread over the image: each frame's tracks are
    binned into a ``grid`` = (columns, rows) of cells over ``size`` = (W, H) px and every cell keeps
    its longest ones (ties: the earlier track) up to its share; the result is the union over frames,
    in the original order. Bounds the bundle adjustments' work on richly textured clips (thousands
    of SIFT tracks) while keeping every frame registered and the points spread over the image."""
    if per_frame <= 0:
        return tracks
    gx, gy = grid
    per_cell = max(1, int(np.ceil(per_frame / (gx * gy))))
    W, H = size
    by_cell: dict[tuple[int, int, int], list[tuple[int, int]]] = {}
    for i, t in enumerate(tracks):
        for f, uv in t.items():
            cx = min(gx - 1, max(0, int(uv[0] * gx / W)))
            cy = min(gy - 1, max(0, int(uv[1] * gy / H)))
            by_cell.setdefault((f, cx, cy), []).append((-len(t), i))
    keep: set[int] = set()
    for cell in sorted(by_cell):
        keep.update(i for _, i in sorted(by_cell[cell])[:per_cell])
    return [tracks[i] for i in sorted(keep)]
