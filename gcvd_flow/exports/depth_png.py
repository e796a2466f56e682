"""``depth-png``: DIR/depth/NNNNNN.png, uint16 millimetres of depth x ``--depth-scale``.

Valid depth is rounded and clipped to 1..65535 mm (a warning counts the clipped pixels),
0 = invalid (``gcvd_flow.io.formats.depth_to_png16``). Monocular: the unit is the run's one
global scale. nerfstudio writes the same files (shared within one export).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gcvd_flow.exports._common import ExportContext, clean_stale, write_bytes
from gcvd_flow.io.formats import depth_to_png16, png_bytes


def depth_to_mm16(depth: np.ndarray, depth_scale: float = 1.0) -> tuple[np.ndarray, int]:
    """float depth (H, W) -> (uint16 millimetres of depth * depth_scale, pixels clipped to 65535)."""
    return depth_to_png16(depth, 1000.0 * depth_scale)


def depth_pngs(ctx: ExportContext) -> dict[str, Any]:
    """Write DIR/depth/ once per export; its details (also nerfstudio's)."""

    def make() -> dict[str, Any]:
        run, d = ctx.run, ctx.out / "depth"
        clipped, names = 0, set()
        for k in range(len(run)):
            mm, c = depth_to_mm16(run.depth(k), ctx.opt.depth_scale)
            clipped += c
            write_bytes(d / f"{run.name(k)}.png", png_bytes(mm))
            names.add(f"{run.name(k)}.png")
        clean_stale(d, names, ".png")
        if clipped:
            ctx.log(f"warning: depth-png: {clipped} pixels exceeded 65.535 m x --depth-scale and were "
                    f"clipped to 65535 mm (use a smaller --depth-scale)")
        return {"dir": str(d), "files": len(run), "unit": "mm", "depth_scale": ctx.opt.depth_scale,
                "clipped_pixels": clipped}

    return ctx.shared("depth", make)


write = depth_pngs
