"""Parameters of the depth stages (depth_fusion, depth_filter, depth_consensus): one frozen
dataclass per stage; the pipeline derives each config section from it (``stages/params.py``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from gcvd_flow.stages.frontend.params import DisPreset
from gcvd_flow.stages.params import param


def _positive_offsets(v: tuple[int, ...]) -> tuple[int, ...]:
    if any(k <= 0 for k in v):
        raise ValueError("offsets are frame distances k > 0 (frames i - k and i + k are used)")
    return tuple(sorted(set(v)))


@dataclass(frozen=True)
class DepthFusionSettings:
    """Optimised depth fused with multi-view triangulation (stages.depth.fusion).

    ``references``: which frames each frame is triangulated against. ``baseline`` (the default
    since 2026-11-25, issue 28): chosen from the final poses by view geometry, the
    fusion_references stage (its settings: ``FusionReferencesSettings``, section
    ``fusion_references``). ``offsets``: the fixed-offset rule of 5261f0f .. a299ec5
    (``offsets``)."""

    enabled: bool = True
    references: Literal["baseline", "offsets"] = param(
        "baseline", "how each frame's references are chosen: 'baseline' by triangulation angle and overlap at "
        "the final poses, 'offsets' the fixed ``offsets``")
    offsets: tuple[int, ...] = param((-8, -4, -2, -1, 1, 2, 4, 8), "references=offsets: reference frames (relative "
                                                                   "index) triangulated against each frame with the "
                                                                   "final poses; +-1 are the flow stage's pairs and "
                                                                   "+-4 the priors' (no new flow); frames far apart "
                                                                   "rarely overlap on a wide-baseline walk")
    preset: DisPreset = "fine"
    fb_thresh: float = param(1.0, "forward-backward consistency, px", gt=0)
    min_angle_deg: float = param(0.2, "smallest usable triangulation angle", ge=0)
    max_log_dev: float = param(0.6, "measurements further from the optimised depth (|log ratio|) are dropped",
                               gt=0)
    agree_log_dev: float = param(0.3, "measurements within this of the optimised depth count as agreeing in "
                                 "the confidence", gt=0)
    coverage_refs: int = param(2, "agreeing references that give a pixel full coverage in the confidence (with "
                               "two offsets: agreeing / references)", ge=1)
    spread_log_sigma: float = param(0.1, "the confidence is scaled by exp(-(s / sigma)^2 / 2), s = the spread (std of "
                                    "log depth, weighted by angle^2) of a pixel's agreeing measurements (0 = off)",
                                    ge=0)


@dataclass(frozen=True)
class FusionReferencesSettings:
    """depth_fusion's references chosen from the final poses (the fusion_references stage, with
    depth_fusion.references=baseline; stages.graph.references.baseline_references): up to
    ``max_refs`` frames within ``max_gap`` that see at least ``min_overlap`` of the frame's depth
    samples at a median triangulation angle in [``min_angle_deg``, ``max_angle_deg``], closest to
    ``target_angle_deg`` (in log), the best one on each side first; a pair whose flow is computed
    anyway (the flow stage's +-1, the priors' flow_far pairs, a pair an earlier frame chose) is
    preferred by ``new_flow_cost``, and a frame adds at most ``max_new_flows`` new flows (the
    fusion_flow stage computes them). Against a299ec5's fixed +-1, 2, 4, 8: synthetic loop
    AbsRel 0.0407 -> 0.0373, ICL 0.0487 -> 0.0479, 300-frame walk 0.0768 -> 0.0788, HoloLens
    0.1430 -> 0.1465 (confident share 48.3 -> 44.5 %), with 0.3-0.7 instead of 1 new flow and at
    most 3 instead of 8 references per frame (docs/benchmarks.md, "Fusion references chosen from
    the poses"). The defaults (2 deg, overlap 0.8, 3 references, 1 new flow, +-12 frames) were
    chosen there from 4 deg / 0.6 / 4 / 2 / 32 (HoloLens confident share 31 %) and neighbours."""

    max_refs: int = param(3, "references per frame at most", ge=1)
    max_gap: int = param(12, "frames searched on each side", ge=1)
    target_angle_deg: float = param(2.0, "median triangulation angle aimed at, degrees",
                                    gt=0)
    min_angle_deg: float = param(0.5, "smallest usable median triangulation angle of a "
                                     "reference, degrees", ge=0)
    max_angle_deg: float = param(20.0, "largest usable median triangulation angle, "
                                     "degrees", gt=0)
    min_overlap: float = param(0.8, "fraction of the frame's points a reference must see",
                               ge=0, le=1)
    new_flow_cost: float = param(0.69, "cost (in |log angle ratio|) of a pair whose flow is "
                                 "not computed anyway", ge=0)
    max_new_flows: int = param(1, "new flows (pairs no other stage computes) a frame may add",
                               ge=0)


@dataclass(frozen=True)
class DepthFilterSettings:
    """CVD2-style depth filter over +-radius neighbours (stages.depth.filter)."""

    enabled: bool = True
    radius: int = param(4, ge=0)
    border: int = param(4, ge=0)
    fill_from: float = param(0.7, "depth confidence of the pixels an edge-aware fill of uncertain depth is "
                             "made from", ge=0, le=1)
    fill_below: float = param(0.0, "pixels less confident than this are pulled towards that fill (in proportion; 0 = "
                                   "off, the default: it helps some clips and hurts others)", ge=0, le=1)


@dataclass(frozen=True)
class DepthConsensusSettings:
    """Filtered depth averaged with what other views see (stages.depth.consensus)."""

    enabled: bool = True
    offsets: tuple[int, ...] = param((8, 16, 24, 32, 48, 64), "references (frames i - k and i + k) whose "
                                     "filtered depth is carried into frame i with the final poses",
                                     validator=_positive_offsets)
    max_log_dev: float = param(0.2, "a carried depth further from frame i's (|log ratio|) is another surface "
                               "(an occlusion) and not used", gt=0)
    reproj_sigma_px: float = param(3.0, "round-trip reprojection error scale, px (weight exp(-(e / sigma)^2))",
                                   gt=0)
    splat_offsets: tuple[int, ...] = param((1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64),
                                           "references (frames i - k and i + k) whose confident filtered depth is "
                                           "splatted forward into frame i after the carry, the correction spread "
                                           "edge-aware (stages.depth.consensus.splat_consensus; () = off)",
                                           validator=_positive_offsets)
    splat_front: float = param(0.1, "splatted depths within this (relative) of the nearest one at a pixel are its "
                               "visible surface and averaged; the rest are occluded", gt=0)
    splat_min_confidence: float = param(0.5, "reference pixels at least this confident are splatted", ge=0, le=1)
    splat_keep: float = param(0.5, "frame i's pixels at least this confident keep their own depth; less confident "
                              "ones take the splat in proportion, (1 - (c / splat_keep)^2) (above 1: every pixel "
                              "blended as first built)", ge=0)
    splat_ref_edge_jump: float = param(0.1, "a reference's pixels within 2 px of a jump of its own log depth larger than "
                                       "this are not splatted (at occlusion boundaries their depth mixes two "
                                       "surfaces); 0 = off", ge=0)
    splat_keep_edges: float = param(0.0, "pixels within 2 px of a jump of frame i's own log depth larger than this "
                                    "keep their depth (0 = off)", ge=0)
    edge_jump: float = param(0.1, "the output confidence is scaled by 0.45 within 2 px of a jump of the output's log depth "
                             "larger than this (an occlusion boundary: a mix of two surfaces); 0 = off", ge=0)
    smooth_lambda: float = param(300.0, "the output's log depth averaged edge-aware over the RGB image, weighted by "
                                 "confidence^2 + 0.01 (a fast global smoother, stages.depth.smooth): its smoothness "
                                 "weight; 0 = off", ge=0)
    smooth_sigma: float = param(0.03, "colour difference (RGB in [0, 1]) at which the smoothing between neighbours "
                                "falls to 1/e", gt=0)
    smooth_keep: float = param(0.7, "pixels at least this confident keep their depth through the smoothing; less "
                               "confident ones take it in proportion, (1 - (c / smooth_keep)^2)", ge=0, le=1)
    tilt_offsets: tuple[int, ...] = param((), "references (frames i - k and i + k) whose images choose, per frame, the "
                                          "slope of the unconfident pixels' log depth about their median "
                                          "(stages.depth.tilt, photometric; () = off)", validator=_positive_offsets)
    tilt_shrink: float = param(0.5, "the chosen slope is moved this far back toward 1 (0: taken as chosen)", ge=0, le=1)
