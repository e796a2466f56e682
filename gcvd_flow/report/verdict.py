"""The report's overall verdict without ground truth: "good", "suspect" or "failed".

Each health signal gets a status from the thresholds below: "ok", "warn" (the run may be off:
suspect), "fail" (the run is not usable: failed) or "info" (shown, never judged). The verdict is
the worst status among the judged signals: any "fail" -> failed, else any "warn" -> suspect,
else good. The signals are self-consistency checks, each one a way a run goes wrong that the run
itself can see:

* multi-view depth agreement: keyframe depth moved by the poses into the next keyframe lands on
  the same depth there (poses and depth that do not fit each other disagree);
* flow consistency: forward-backward consistent flow between adjacent frames (everything
  downstream is built on the flow);
* keyframes: at least three, and no gap of half the clip or as long as ``keyframes.max_gap``
  (the optimisation sees the frames in between only through the flow);
* bundle adjustment: enough flow tracks (3+ keyframes) to check the poses against; the median
  reprojection error of the pose graph's poses on them (how far the optimisation of depth and
  poses is from the measured tracks) and after adjustment (what is left), as angles;
* scale spread (shown, not judged): the per-keyframe depth scale bundle adjustment applied (max /
  min). It measures how much scale drift of the keyframe chain the adjustment corrected, not what
  is left: the real HoloLens walk (ATE 0.86 % of its path, window scales 0.97-1.13 after the
  adjustment) needs 6.8 because its chain drifts 0.8-5.0 before it; the depth-scale disagreement
  that remains shows in the multi-view depth agreement;
* loop edges found but none kept by the pose graph, or a pose graph whose residual grew;
* valid depth and static pixels under half the image (warn), and a missing cache (warn: the
  checks above that read stage outputs cannot run). Guessed intrinsics are shown, not judged.

The thresholds were set on runs with ground truth (``benchmarks/bench_verdict.py``, the table in
docs/benchmarks.md): every run there with ATE > 5 % of the path is suspect or failed, none under
1 % is. That set is small and the thresholds were fitted on it (in-sample): treat "good" as
"nothing the run can see is wrong", not as a guarantee.
"""

from __future__ import annotations

from dataclasses import dataclass

#: (warn below, fail below) for shares in [0, 1]; (warn above, fail above) for the others.
# Re-fitted 2026-11-28 on the 23 runs of benchmarks/bench_verdict.py with the code of that day
# (docs/benchmarks.md): good runs (ATE < 1 % of the path) agree on >= 71.6 % of pixels, a broken
# one (5 steps, no BA, 5.4 %) on 61.3 %; the real HoloLens walk (0.86 %) has 62.7 % consistent
# flow (motion blur, sensor noise), the broken scans 24-40 %.
AGREEMENT = (0.66, 0.20)
FLOW_CONSISTENCY = (0.60, 0.45)
# bundle adjustment's median reprojection error as an angle (px / fx, mrad: the same at every
# resolution). Before: how far the pose graph's poses are from explaining the flow tracks (good
# runs of the validation set: <= 7.0 mrad, ICL at 128 px; broken ones 16-28); after: what is left.
BA_BEFORE_MRAD = (10.0, 20.0)
BA_AFTER_MRAD = (5.0, 15.0)
BA_MIN_TRACKS = 30
MIN_KEYFRAMES = 3
MAX_GAP_SHARE = 0.5  # a keyframe gap of half the clip or more: suspect

VERDICTS = ("good", "suspect", "failed")


@dataclass
class Signal:
    """One health signal: label, value as text, status ("ok" | "warn" | "fail" | "info"),
    explanation; ``judged`` False keeps it out of the verdict (e.g. guessed intrinsics)."""

    label: str
    value: str
    status: str
    detail: str = ""
    judged: bool = True


def low_is_bad(x: float, limits: tuple[float, float]) -> str:
    """Status of a share where low is bad: "fail" below limits[1], "warn" below limits[0]."""
    return "fail" if x < limits[1] else "warn" if x < limits[0] else "ok"


def high_is_bad(x: float, limits: tuple[float, float]) -> str:
    """Status of a value where high is bad: "fail" above limits[1], "warn" above limits[0]."""
    return "fail" if x > limits[1] else "warn" if x > limits[0] else "ok"


def keyframe_status(n_frames: int, n_keyframes: int, max_gap_frames: int, max_gap_setting: int) -> str:
    """Keyframes: too few -> fail; a gap of half the clip or at keyframes.max_gap -> warn."""
    if n_keyframes < MIN_KEYFRAMES:
        return "fail"
    if max_gap_frames >= max_gap_setting or max_gap_frames >= MAX_GAP_SHARE * n_frames:
        return "warn"
    return "ok"


def ba_status(tracks: int, before_mrad: float, after_mrad: float) -> str:
    """Bundle adjustment: too few tracks -> fail; else the worse of before / after."""
    if tracks < BA_MIN_TRACKS:
        return "fail"
    st = {high_is_bad(before_mrad, BA_BEFORE_MRAD), high_is_bad(after_mrad, BA_AFTER_MRAD)}
    return "fail" if "fail" in st else "warn" if "warn" in st else "ok"


def overall(signals: list[Signal]) -> str:
    """"failed" if a judged signal fails, else "suspect" if one warns, else "good"."""
    st = {s.status for s in signals if s.judged}
    return "failed" if "fail" in st else "suspect" if "warn" in st else "good"


def health_json(signals: list[Signal]) -> list[dict[str, str]]:
    """[{"name", "value", "status"}] for `report --json`."""
    return [{"name": s.label, "value": s.value, "status": s.status} for s in signals]
