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
4. A TF-IDF bag of words over a two-level vocabulary tree (32 x 32 words, same k-means) gives
   a second score: two views score by the rare words they share.
5. Scoring over all keyframe pairs more than ``min_separation`` keyframes apart
   (:func:`relative_candidates`): each kind's cosine similarity is averaged along the path (a
   revisit lasts several keyframes, walked again in the same or the opposite direction; a
   chance look-alike stands alone: :func:`sequence_scores`) and divided by the keyframes'
   similarity with their temporal neighbours (which overlap with them by construction), then
   standardised and averaged over the kinds. A pair counts only when the path left in between
   (:func:`departure`); each keyframe proposes its ``top_k`` best partners, kept when the
   neighbour-relative score reaches ``min_ratio`` (DBoW2's normalised score: absolute scores
   depend on how textured a view is). The candidates are ranked by score and capped by the caller.

Measured on the real HoloLens walk-through (81 keyframes, 256x170, ~250 SIFT features each;
benchmarks/bench_retrieval.py, docs/benchmarks.md): of the 28 revisit pairs (>= 15 frames apart,
within 0.5 m and 30 deg) 20 are among the 40 candidates (the whole-image descriptor: none); of
the 59 pairs sharing >= 30 % of their ground-truth depth points, 31; every verified edge true.
VLAD alone finds the real revisits but none on the synthetic room (procedural textures), the bag
of words the synthetic ones: hence both, standardised and averaged. Scores shift by a few pairs
with the vocabulary (k-means subset / seed).

Deterministic: the subset, initialisation and iterations are fixed for a seed; ties break by
index. Pure functions, numpy + nothing else.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from gcvd_flow.stages.graph.params import AssociationSettings

DEFAULT_WORDS = AssociationSettings.words
_A = AssociationSettings  # the defaults are the association stage's, written once there
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


def departure(score: np.ndarray) -> np.ndarray:
    """(N, N) for each pair a < b (and mirrored): how far the path left between them, score[a, b]
    minus the larger of min_{a<c<b} score[a, c] and min_{a<c<b} score[c, b] (-inf without a
    keyframe between). A revisit returns after going elsewhere: some keyframe between scores
    lower with both ends than they score together (> 0). Forward motion sees the same scene
    ahead ever smaller: the keyframes between score higher with both ends (< 0)."""
    s = np.asarray(score, np.float64)
    n = s.shape[0]
    out = np.full((n, n), -np.inf)
    for a in range(n):
        run_a = np.minimum.accumulate(s[a, a + 1:]) if a + 1 < n else np.zeros(0)  # min_{a<c<=b} s[a, c]
        for b in range(a + 2, n):
            from_a = run_a[b - a - 2]  # min over a < c < b
            from_b = s[a + 1:b, b].min()
            out[a, b] = out[b, a] = s[a, b] - max(from_a, from_b)
    return out


def relative_candidates(descs: np.ndarray | Sequence[np.ndarray], min_separation: int = _A.min_separation,
                        top_k: int = _A.top_k, min_ratio: float = _A.min_ratio, window: int = _A.window,
                        min_departure: float | None = _A.min_departure) -> list[tuple[int, int, float]]:
    """Loop candidates over all keyframe pairs from one or more descriptor kinds.

    Per kind: cosine similarity averaged along the path (:func:`sequence_scores`, ``window``),
    divided by the geometric mean of the two keyframes' :func:`neighbour_scores` (1 = as alike
    as a keyframe and its temporal neighbour). Kinds are put on one scale by standardising that
    relative score over the eligible pairs (mean 0, std 1) and averaged: the ranking score.

    Args:
        descs: one (N, D) array or a sequence of (N, D_k) arrays of L2-normalised descriptors
            of the same N keyframes in keyframe order (e.g. VLAD and bag of words).
        min_separation: only pairs |b - a| > min_separation are eligible.
        top_k: each keyframe proposes its top_k best-ranked eligible partners (before or after).
        min_ratio: a proposal is kept when its relative score reaches min_ratio in at least one
            kind (a bland view scores low with everything, a textured one high: relative to
            the neighbours, not absolute).
        window: :func:`sequence_scores` half-window (keyframes).
        min_departure: a pair is eligible only when the path left in between: its
            :func:`departure` on the ranking score >= this (standard deviations; None: off).
            Forward driving (KITTI 07) sees the road ahead again 9+ keyframes later: geometrically
            sound overlaps whose edges wrecked its pose graph (ATE 1.90 -> 3.14 m with 16).
    Returns:
        [(a, b, score)] a < b keyframe positions, each pair once, sorted by decreasing ranking
        score, then (a, b).
    """
    kinds = [descs] if isinstance(descs, np.ndarray) else list(descs)
    n = int(np.asarray(kinds[0]).shape[0]) if kinds else 0
    if n == 0:
        return []
    idx = np.arange(n)
    eligible = np.abs(idx[:, None] - idx[None, :]) > int(min_separation)
    if not eligible.any():
        return []
    score = np.zeros((n, n))
    best_rel = np.full((n, n), -np.inf)
    for dd in kinds:
        d = np.asarray(dd, np.float64)
        if d.shape[0] != n:
            raise ValueError(f"descriptor kinds disagree on the number of keyframes ({d.shape[0]} != {n})")
        sim = d @ d.T
        ref = np.maximum(neighbour_scores(sim), 1e-6)
        rel = sequence_scores(sim, window) / np.sqrt(ref[:, None] * ref[None, :])
        best_rel = np.maximum(best_rel, rel)
        v = rel[eligible]
        score += (rel - v.mean()) / max(float(v.std()), 1e-9) / len(kinds)
    if min_departure is not None:
        eligible &= departure(score) >= min_departure
    masked = np.where(eligible, score, -np.inf)
    order = np.argsort(-masked, axis=1, kind="stable")[:, : max(int(top_k), 0)]
    keep = set()
    for a in range(n):
        for b in order[a]:
            if eligible[a, b] and best_rel[a, b] >= min_ratio:
                keep.add((min(a, int(b)), max(a, int(b))))
    out = [(a, b, float(score[a, b])) for a, b in keep]
    out.sort(key=lambda t: (-t[2], t[0], t[1]))
    return out


def build_tree(descs: Sequence[np.ndarray], branch: int = 32, max_samples: int = DEFAULT_MAX_SAMPLES,
               iters: int = DEFAULT_ITERS, seed: int = 0) -> tuple[np.ndarray, list[np.ndarray]]:
    """Two-level vocabulary tree: ``branch`` coarse words, each split into at most ``branch``
    fine words (k-means of its own samples). Returns (coarse (B, 128), [fine (B_c, 128) per
    coarse word]) float32."""
    x = np.concatenate([np.asarray(d, np.float32) for d in descs]) if len(descs) else np.zeros((0, 128), np.float32)
    if len(x) > max_samples:
        x = x[np.linspace(0, len(x) - 1, int(max_samples)).round().astype(np.int64)]
    coarse = build_vocabulary([x], words=branch, max_samples=max_samples, iters=iters, seed=seed)
    if len(coarse) == 0:
        return coarse, []
    lab = np.argmin(_sq_dists(x.astype(np.float64), coarse.astype(np.float64)), axis=1)
    fine = [build_vocabulary([x[lab == c]], words=branch, max_samples=max_samples, iters=iters, seed=seed + 1 + c)
            for c in range(len(coarse))]
    return coarse, fine


def quantise(des: np.ndarray, coarse: np.ndarray, fine: list[np.ndarray]) -> np.ndarray:
    """(M,) int64 word ids (coarse id * branch + fine id, branch = len(coarse)) of RootSIFT (M, 128)."""
    if len(des) == 0 or len(coarse) == 0:
        return np.zeros(0, np.int64)
    x = np.asarray(des, np.float64)
    c = np.argmin(_sq_dists(x, coarse.astype(np.float64)), axis=1)
    out = np.zeros(len(x), np.int64)
    b = len(coarse)
    for k in np.unique(c):
        sel = c == k
        f = fine[int(k)]
        sub = np.argmin(_sq_dists(x[sel], f.astype(np.float64)), axis=1) if len(f) else np.zeros(int(sel.sum()), np.int64)
        out[sel] = int(k) * b + sub
    return out


def bow_descriptors(descs: Sequence[np.ndarray | None], branch: int = 32, max_samples: int = DEFAULT_MAX_SAMPLES,
                    iters: int = DEFAULT_ITERS, seed: int = 0) -> np.ndarray:
    """(N, branch**2) float32 TF-IDF bag-of-words vectors (L2-normalised) of N keyframes' raw
    SIFT descriptors, with a two-level vocabulary tree learned from these keyframes."""
    roots = [rootsift(d) for d in descs]
    coarse, fine = build_tree(roots, branch=branch, max_samples=max_samples, iters=iters, seed=seed)
    nw = max(len(coarse), 1) ** 2
    tf = np.zeros((len(roots), nw), np.float64)
    for k, r in enumerate(roots):
        w = quantise(r, coarse, fine)
        if len(w):
            tf[k] = np.bincount(w, minlength=nw) / len(w)
    df = (tf > 0).sum(0)
    idf = np.where(df > 0, np.log(max(len(roots), 1) / np.maximum(df, 1)), 0.0)
    v = tf * idf
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return (v / np.maximum(n, 1e-12)).astype(np.float32)
