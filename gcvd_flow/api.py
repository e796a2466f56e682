"""The gcvd-flow Python API: the CLI's verbs, with the GCVD pipeline as the default.

    from gcvd_flow import api
    res = api.run(api.Invocation(input="walk.mp4", out="runs/walk", sets=["keyframes.delta=0.15"]))
    plan = api.plan(api.Invocation(input="walk.mp4", out="runs/walk"))
"""

from __future__ import annotations

from dataclasses import dataclass

from gcvd_flow.engine import api as _engine
from gcvd_flow.engine.api import (fsck, gc, open_store, plan, read_run_dir, recorded_output, run, status,
                                  why)

PIPELINE = "gcvd"


@dataclass
class Invocation(_engine.Invocation):
    pipeline: str = PIPELINE


__all__ = ["Invocation", "run", "plan", "why", "status", "recorded_output", "fsck", "gc", "open_store",
           "read_run_dir"]
