"""Loop-candidate retrieval from the clip's own local features: a VLAD vocabulary (no weights).

The whole-image descriptor of :mod:`stages.graph.association` keeps *where* structure is in the
image, so a place seen again 15-30 deg apart scores like a different place (the real HoloLens
walk-through: 3 of 28 revisit pairs above its threshold). Local features do not care where in
the image they are. So:

1. Every keyframe's SIFT descriptors (already computed for verification) become RootSIFT
   (L1-normalise, square root: Hellinger kernel).
2. A vocabulary of ``words`` visual words is learned from the clip's own keyframes: k-means on
   at most ``max_samples`` descriptors (an evenly strided subset), k-means++ initialisation from
   a fixed seed, ``iters`` Lloyd iterations. No weights are downloaded; the words fit the scene.
3. Each keyframe becomes a VLAD vector (Jegou et al. 2010; Arandjelovic & Zisserman, "All about
   VLAD", 2013): per word, the sum of its descriptors' residuals to the word centre,
   intra-normalised per word, signed-square-rooted and L2-normalised. Words a keyframe does not
   use contribute zeros, so two views score by the words (places) they share.
4. Scoring over all keyframe pairs more than ``min_separation`` keyframes apart: the cosine
   similarity is averaged along the path (a revisit lasts several keyframes, walked again in the
   same or the opposite direction; a chance look-alike stands alone: :func:`sequence_scores`);
   each keyframe proposes its ``top_k`` best-scoring eligible partners, kept when the score is at
   least ``min_ratio`` times the keyframe's similarity with its temporal neighbours (which
   overlap with it by construction: keyframes are about one keyframe threshold of motion apart).
   Relative to the neighbours because absolute VLAD scores depend on how textured a view is
   (DBoW2's normalised score). The candidates are ranked by score and capped by the caller.

Measured on the real HoloLens walk-through (81 keyframes, 256x170, ~250 SIFT features each;
benchmarks/bench_retrieval.py): of the 28 revisit pairs (>= 15 frames apart, within 0.5 m and
30 deg) 16-19 are among the 40 best candidates (the whole-image descriptor: 3 above its
threshold, 8 among its 40 best); of the 59 pairs sharing >= 30 % of their ground-truth depth
points, 24-29. The ranking varies by a few pairs with the vocabulary (k-means subset / seed).

Deterministic: the subset, initialisation and iterations are fixed for a seed; ties break by
index. Pure functions, numpy + nothing else.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

DEFAULT_WORDS = 64
DEFAULT_MAX_SAMPLES = 20000
DEFAULT_ITERS = 12


def rootsift(des: np.ndarray | None) -> np.ndarray:
    """RootSIFT of SIFT descriptors: (M, 128) float32 (M = 0 for None)."""
    if des is None or len(des) == 0:
        return np.zeros((0, 128), np.float32)
    d = np.asarray(des, np.float64)
    d = d / np.maximum(np.abs(d).sum(axis=1, keepdims=True), 1e-12)
    return np.sqrt(d).astype(np.float32)


def _sq_dists(x: np.ndarray, c: np.ndarray, xx: np.ndarray | None = None) -> np.ndarray:
    """(M, K) squared Euclidean distances of rows of x (M, D) float64 to centres c (K, D)
    float64; ``xx``: the rows' squared norms (M,) when already known."""
    xx = (x * x).sum(1) if xx is None else xx
    d = xx[:, None] - 2.0 * (x @ c.T) + (c * c).sum(1)[None, :]
    return np.maximum(d, 0.0)


def _group_sums(x: np.ndarray, lab: np.ndarray, k: int) -> np.ndarray:
    """(k, D) float64 sums of the rows of x (M, D) per label lab (M,) in [0, k) (fixed order)."""
    out = np.zeros((k, x.shape[1]), np.float64)
    if len(x) == 0:
        return out
    order = np.argsort(lab, kind="stable")
    sl = lab[order]
    starts = np.flatnonzero(np.r_[True, sl[1:] != sl[:-1]])
    out[sl[starts]] = np.add.reduceat(x[order], starts, axis=0)
    return out


def build_vocabulary(descs: Sequence[np.ndarray], words: int = DEFAULT_WORDS, max_samples: int = DEFAULT_MAX_SAMPLES,
                     iters: int = DEFAULT_ITERS, seed: int = 0) -> np.ndarray:
    """k-means visual words of RootSIFT descriptors.

    Args:
        descs: per keyframe (M_k, 128) RootSIFT descriptors.
        words: number of words K (fewer when there are fewer distinct descriptors).
        max_samples: at most this many descriptors train the words (evenly strided subset).
        iters: Lloyd iterations after the k-means++ initialisation.
        seed: RNG seed of the initialisation.
    Returns:
        (K', 128) float32 centres, K' = min(words, number of samples); (0, 128) without samples.
    """
    x = np.concatenate([np.asarray(d, np.float32) for d in descs]) if len(descs) else np.zeros((0, 128), np.float32)
    if len(x) > max_samples:
        x = x[np.linspace(0, len(x) - 1, int(max_samples)).round().astype(np.int64)]
    k = min(int(words), len(x))
    if k == 0:
        return np.zeros((0, 128), np.float32)
    x64 = x.astype(np.float64)
    rng = np.random.default_rng(seed)
    # k-means++ initialisation
    centres = np.empty((k, x.shape[1]), np.float64)
    xx = (x64 * x64).sum(1)
    centres[0] = x64[int(rng.integers(len(x64)))]
    d2 = _sq_dists(x64, centres[:1], xx)[:, 0]
    for m in range(1, k):
        total = d2.sum()
        idx = int(rng.choice(len(x64), p=d2 / total)) if total > 0 else int(rng.integers(len(x64)))
        centres[m] = x64[idx]
        d2 = np.minimum(d2, _sq_dists(x64, centres[m:m + 1], xx)[:, 0])
    for _ in range(int(iters)):
        dist = _sq_dists(x64, centres, xx)
        lab = np.argmin(dist, axis=1)
        counts = np.bincount(lab, minlength=k)
        sums = _group_sums(x64, lab, k)
        empty = counts == 0
        centres[~empty] = sums[~empty] / counts[~empty, None]
        if empty.any():  # re-seed an empty word at the sample farthest from its centre
            far = np.argsort(-dist[np.arange(len(x64)), lab], kind="stable")[: int(empty.sum())]
            centres[np.nonzero(empty)[0]] = x64[far]
    return centres.astype(np.float32)


def vlad(des: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """VLAD vector of one image's RootSIFT descriptors.

    Args:
        des: (M, 128) RootSIFT descriptors; centres: (K, 128) visual words.
    Returns:
        (K * 128,) float32, intra-normalised per word, signed square root, L2-normalised
        (all zeros without descriptors).
    """
    k, dim = centres.shape
    out = np.zeros((k, dim), np.float64)
    if len(des) and k:
        x = np.asarray(des, np.float64)
        lab = np.argmin(_sq_dists(x, centres.astype(np.float64)), axis=1)
        out = _group_sums(x - centres[lab].astype(np.float64), lab, k)
        norms = np.linalg.norm(out, axis=1, keepdims=True)
        out = np.where(norms > 0, out / np.maximum(norms, 1e-12), 0.0)
    v = (np.sign(out) * np.sqrt(np.abs(out))).ravel()
    n = np.linalg.norm(v)
    return (v / n if n > 0 else v).astype(np.float32)


def vlad_descriptors(descs: Sequence[np.ndarray | None], words: int = DEFAULT_WORDS,
                     max_samples: int = DEFAULT_MAX_SAMPLES, iters: int = DEFAULT_ITERS, seed: int = 0) -> np.ndarray:
    """(N, K * 128) float32 VLAD descriptors of N keyframes from their raw SIFT descriptors
    (each (M_k, 128) or None), with a vocabulary learned from these keyframes."""
    roots = [rootsift(d) for d in descs]
    centres = build_vocabulary(roots, words=words, max_samples=max_samples, iters=iters, seed=seed)
    if len(centres) == 0:
        return np.zeros((len(roots), 1), np.float32)
    return np.stack([vlad(r, centres) for r in roots]) if roots else np.zeros((0, centres.size), np.float32)


def neighbour_scores(sim: np.ndarray) -> np.ndarray:
    """(N,) each keyframe's mean similarity with its temporal neighbours (previous and next
    keyframe; the one there is at the ends; 1 for a single keyframe)."""
    n = sim.shape[0]
    if n < 2:
        return np.ones(n)
    nxt = np.diagonal(sim, 1)
    ref = np.empty(n)
    ref[0], ref[-1] = nxt[0], nxt[-1]
    ref[1:-1] = 0.5 * (nxt[:-1] + nxt[1:])
    return ref


def sequence_scores(score: np.ndarray, window: int = 1) -> np.ndarray:
    """Scores (N, N) averaged along a short stretch of the path: a revisit lasts several keyframes,
    walked again in the same or the opposite direction, so the pairs (a + d, b + d) (same
    direction) or (a + d, b - d) (opposite), |d| <= window, score alike while a chance look-alike
    stands alone. Returns the larger of the two means (over the pairs inside the matrix) per
    pair, (N, N) float64, symmetric when ``score`` is; ``window`` 0 returns ``score``."""
    s = np.asarray(score, np.float64)
    n = s.shape[0]
    w = int(window)
    if w <= 0 or n == 0:
        return s.copy()
    p = np.pad(s, w, constant_values=np.nan)
    means = []
    for sign in (1, -1):
        tot = np.zeros_like(s)
        cnt = np.zeros_like(s)
        for d in range(-w, w + 1):
            v = p[w + d:w + d + n, w + sign * d:w + sign * d + n]
            ok = np.isfinite(v)
            tot += np.where(ok, v, 0.0)
            cnt += ok
        means.append(tot / cnt)
    return np.maximum(means[0], means[1])


def relative_candidates(desc: np.ndarray, min_separation: int = 8, top_k: int = 5, min_ratio: float = 0.1,
                        window: int = 1) -> list[tuple[int, int, float]]:
    """Loop candidates over all keyframe pairs.

    Args:
        desc: (N, D) L2-normalised descriptors in keyframe order.
        min_separation: only pairs |b - a| > min_separation are eligible.
        top_k: each keyframe proposes its top_k best-scoring eligible partners (before or after);
            score = cosine similarity averaged along the path (:func:`sequence_scores`, ``window``).
        min_ratio: a proposal is kept when its score is >= min_ratio x the lower of the two
            keyframes' :func:`neighbour_scores` (how alike a keyframe and its temporal neighbour
            are: a textured view scores high with everything, a bland one low).
        window: :func:`sequence_scores` half-window (keyframes).
    Returns:
        [(a, b, score)] a < b keyframe positions, each pair once, sorted by decreasing score,
        then (a, b).
    """
    d = np.asarray(desc, np.float64)
    n = d.shape[0]
    if n == 0:
        return []
    sim = d @ d.T
    score = sequence_scores(sim, window)
    ref = np.maximum(neighbour_scores(sim), 1e-6)
    ratio = score / np.minimum(ref[:, None], ref[None, :])
    idx = np.arange(n)
    eligible = np.abs(idx[:, None] - idx[None, :]) > int(min_separation)
    masked = np.where(eligible, score, -np.inf)
    order = np.argsort(-masked, axis=1, kind="stable")[:, : max(int(top_k), 0)]
    keep = set()
    for a in range(n):
        for b in order[a]:
            if eligible[a, b] and ratio[a, b] >= min_ratio:
                keep.add((min(a, int(b)), max(a, int(b))))
    out = [(a, b, float(score[a, b])) for a, b in keep]
    out.sort(key=lambda t: (-t[2], t[0], t[1]))
    return out
