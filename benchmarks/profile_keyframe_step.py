"""Where a keyframe-window Adam step spends its time: the depth decode (done once per step for
all the window's frames), the rest of the loss (the sampled pairs' warps, samples and losses),
and backward + optimiser step. Decides how much splitting a window's pairs over two processes
could gain (the decode would be done by both).

    .venv/bin/python benchmarks/profile_keyframe_step.py CLIP [gcvd-flow run options ...]

runs ``gcvd-flow run CLIP --until optimize_keyframes --jobs 1 ...`` in this process with the
solver's step timed, and prints the totals (seconds) and the per-step means (ms) as JSON. Use a
cache whose front stages are done (``--cache``) and a fresh setting of the keyframe stage (e.g.
``--set optimize_keyframes.steps=30``) so that it runs.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gcvd_flow import cli  # noqa: E402
from gcvd_flow.stages.models import depth_net  # noqa: E402
from gcvd_flow.stages.optimize import solver  # noqa: E402

TOTALS = {"decode": 0.0, "loss": 0.0, "backward_step": 0.0, "split_step": 0.0, "steps": 0}


def _timed_decode(original):
    def decode(self, *args, **kwargs):
        t = time.perf_counter()
        out = original(self, *args, **kwargs)
        TOTALS["decode"] += time.perf_counter() - t
        return out
    return decode


_ORIGINAL_STEP = solver.Solver.step


def _timed_step(self, gen):
    """Solver.step with its two halves timed (same arithmetic as the original); a window split into
    pair blocks (``optimize_keyframes.pair_blocks`` > 1) is timed as a whole, under "split_step"."""
    if len(self.blocks) > 1:
        t = time.perf_counter()
        loss = _ORIGINAL_STEP(self, gen)
        TOTALS["split_step"] += time.perf_counter() - t
        TOTALS["steps"] += 1
        return loss
    self.opt.zero_grad()
    t0 = time.perf_counter()
    loss = self.loss(gen)
    t1 = time.perf_counter()
    loss.backward()
    self.opt.step()
    TOTALS["loss"] += t1 - t0
    TOTALS["backward_step"] += time.perf_counter() - t1
    TOTALS["steps"] += 1
    return float(loss.detach())


def main() -> None:
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    depth_net.DepthNet.decode = _timed_decode(depth_net.DepthNet.decode)
    solver.Solver.step = _timed_step
    code = cli.main(["run", *sys.argv[1:], "--until", "optimize_keyframes", "--jobs", "1"])
    n = max(TOTALS["steps"], 1)
    doc = {"exit": code, **{k: round(v, 3) for k, v in TOTALS.items()},
           "per_step_ms": {k: round(1000 * TOTALS[k] / n, 1) for k in ("decode", "loss", "backward_step", "split_step")}}
    print(json.dumps(doc))


if __name__ == "__main__":
    main()
