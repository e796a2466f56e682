"""``tum``: DIR/poses.txt, a byte copy of the run's TUM trajectory (written by
``gcvd_flow.io.formats.write_tum_poses``, the one TUM writer: ``t tx ty tz qx qy qz qw``,
camera-to-world, ``t`` = source frame index)."""

from __future__ import annotations

from typing import Any

from gcvd_flow.exports._common import ExportContext, write_bytes


def write(ctx: ExportContext) -> dict[str, Any]:
    src = ctx.run.run_dir / "poses.txt"
    dst = ctx.out / "poses.txt"
    write_bytes(dst, src.read_bytes())
    return {"file": str(dst), "poses": len(ctx.run)}
