"""Parameters of the keyframe graph stages (keyframes, association): one frozen dataclass per
stage; the pipeline derives each config section from it (``stages/params.py``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from gcvd_flow.stages.params import WEIGHTS_FILE, param


@dataclass(frozen=True)
class KeyframesSettings:
    """Keyframe selection by accumulated static-scene flow (stages.graph.keyframes)."""

    enabled: bool = True
    delta: float = param(0.1, "accumulated flow threshold, fraction of min(H, W)", gt=0)
    max_gap: int = param(39, ge=1)


@dataclass(frozen=True)
class AssociationSettings:
    """Loop candidates and the keyframe graph (stages.graph.association)."""

    enabled: bool = True
    backend: Literal["default", "resnet18"] = "default"
    weights: str | None = param(None, "ResNet-18 weights file", json_schema_extra=WEIGHTS_FILE)
    threshold: float | None = param(None, "descriptor similarity threshold (None: backend default)")
    nms: int = param(8, ge=0)
    min_separation: int = param(8, ge=0)
    min_inlier_ratio: float = param(0.5, ge=0, le=1)
    min_consistent: float = param(0.1, ge=0, le=1)
    per_keyframe: int = param(0, "candidates also: each keyframe's most similar eligible partners (a revisit lasting "
                                 "several keyframes gives several loop edges); 0: NMS only", ge=0)
    max_candidates: int = param(40, "loop candidates verified at most (the most similar)", ge=0)
    retrieval: Literal["vocabulary", "global"] = param(
        "global", "loop candidates: global (the whole-image descriptor with threshold / nms / per_keyframe) or "
                  "vocabulary (VLAD + TF-IDF bag of words of the clip's own keyframes' SIFT features over all "
                  "keyframe pairs; opt-in: it finds revisits the global descriptor misses, and on forward driving "
                  "look-alikes ahead); resnet18 is global")
    words: int = param(64, "vocabulary: VLAD visual words (k-means on the keyframes' RootSIFT, fixed seed)", ge=1)
    top_k: int = param(5, "vocabulary: candidates each keyframe proposes (its best-scoring partners)", ge=0)
    min_ratio: float = param(0.1, "vocabulary: a candidate's similarity relative to its keyframes' similarity "
                             "with their temporal neighbours must reach this (in VLAD or bag of words)", ge=0)
    loop_nms: int = param(8, "verified loop edges kept: the best (most inliers) within +-loop_nms/2 keyframes at both"
                             " ends; <= 1 keeps all", ge=0)
    min_departure: float = param(0.5, "vocabulary: a pair is a candidate only when the path left in between (some "
                                      "keyframe between scores lower with both ends, by this many standard "
                                      "deviations): forward driving sees the road ahead again, which is no revisit", ge=0)
    window: int = param(1, "vocabulary: scores averaged over +-window keyframes along the path (a revisit lasts "
                        "several keyframes)", ge=0)
    prewarp_sequential: Literal["auto", "on", "off"] = param(
        "auto", "pre-warp consecutive keyframes by their RANSAC homography before the flow, as loop candidates are: "
                "on, off, or auto: on unless the clip moves forward (>= 80 % of the consecutive pairs' SIFT "
                "translations within 30 degrees of the optical axis), where the homography (a zoom fitted to a 3-D "
                "street) biases the parallax into scale drift")
    verify: Literal["geometric", "paper"] = param(
        "geometric", "loop verification: geometric (essential-matrix inliers and the dense flow agreeing with "
        "them; accepts wide-baseline revisits) or paper (mean flow <= the keyframe threshold)")
    min_inliers: int = param(20, "geometric: essential-matrix (or homography) inliers a loop needs (forward-motion "
                                 "look-alikes verify with fewer inliers than true revisits)", ge=5)
    min_epipolar: float = param(0.5, "geometric: share of consistent flow within 2 px of the matches' epipolar "
                                "geometry", ge=0, le=1)

    def check(self) -> None:
        if self.backend == "resnet18" and not self.weights:
            raise ValueError("association.backend=resnet18 needs association.weights=FILE "
                             "(torchvision resnet18, .pth or .safetensors)")
