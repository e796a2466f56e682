"""``depth-png``: DIR/depth/NNNNNN.png, uint16 millimetres of depth x ``--depth-scale``, and
DIR/confidence/NNNNNN.png, uint16 round(confidence x 65535), when the run has confidence/.

Valid depth is rounded and clipped to 1..65535 mm (a warning counts the clipped pixels),
0 = invalid (``gcvd_flow.io.formats.depth_to_png16``). Monocular: the unit is the run's one
global scale. The confidence is a second 16-bit grey PNG of the same size rather than an alpha
channel, so that the depth PNG stays the plain 16-bit grey image depth readers (nerfstudio,
Open3D, TUM / Redwood tools) expect. A run dir without confidence/ gets no confidence/ PNGs.
nerfstudio writes the same files (shared within one export).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gcvd_flow.exports._common import ExportContext, clean_stale, write_bytes
from gcvd_flow.exports.confidence import confidence_to_u16
from gcvd_flow.io.formats import depth_to_png16, png_bytes


def depth_to_mm16(depth: np.ndarray, depth_scale: float = 1.0) -> tuple[np.ndarray, int]:
    """float depth (H, W) -> (uint16 millimetres of depth * depth_scale, pixels clipped to 65535)."""
    return depth_to_png16(depth, 1000.0 * depth_scale)


def depth_pngs(ctx: ExportContext) -> dict[str, Any]:
    """Write DIR/depth/ once per export; its details (also nerfstudio's)."""

    def make() -> dict[str, Any]:
        run, d, dc = ctx.run, ctx.out / "depth", ctx.out / "confidence"
        clipped, names = 0, set()
        for k in range(len(run)):
            mm, c = depth_to_mm16(run.depth(k), ctx.opt.depth_scale)
            clipped += c
            write_bytes(d / f"{run.name(k)}.png", png_bytes(mm))
            if run.has_confidence:
                write_bytes(dc / f"{run.name(k)}.png", png_bytes(confidence_to_u16(run.confidence(k))))
            names.add(f"{run.name(k)}.png")
        clean_stale(d, names, ".png")
        clean_stale(dc, names if run.has_confidence else set(), ".png")
        if clipped:
            ctx.log(f"warning: depth-png: {clipped} pixels exceeded 65.535 m x --depth-scale and were "
                    f"clipped to 65535 mm (use a smaller --depth-scale)")
        return {"dir": str(d), "files": len(run), "unit": "mm", "depth_scale": ctx.opt.depth_scale,
                "clipped_pixels": clipped,
                "confidence_dir": str(dc) if run.has_confidence else None}

    return ctx.shared("depth", make)


write = depth_pngs
