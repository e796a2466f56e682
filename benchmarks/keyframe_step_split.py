"""CPU time of a keyframe-window Adam step by part, uniform points per pair against points by pair
weight (issue 28): process CPU time (``time.process_time``, so descheduled time under load does not
count), one torch thread, one pair block, on the first window with at least ``--min-pairs`` pairs.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/keyframe_step_split.py CLIP --cache CACHE \\
        --set optimize_keyframes.steps=7 [gcvd-flow run options ...]

runs ``gcvd-flow run CLIP --until optimize_keyframes --jobs 1 --set optimize_keyframes.pair_blocks=1``
in this process; at the first window with enough pairs it times 4 x 6 steps of fresh solvers on that
window (uniform, by weight, uniform, by weight), prints per-step means (ms) as JSON and exits. Use a
cache whose front stages are done and a fresh setting of the keyframe stage so that it runs.

    .venv/bin/python benchmarks/keyframe_step_split.py --curves OUT.json CLIP [run options ...]

instead records every step's loss of every solver the run creates (keyframe windows, and with
``--jobs 1`` segment windows and loop edges), with its window size, pairs and trainable poses.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402

from gcvd_flow import cli  # noqa: E402
from gcvd_flow.stages.optimize import (
    keyframes as KF,  # noqa: E402
    solver as S,  # noqa: E402
)

PARTS = ("decode", "pair_losses", "regularisers", "backward", "adam")
TOTALS: dict[str, dict[str, float]] = {}


def _timed_step(s: S.Solver, gen: torch.Generator) -> None:
    """One Solver.step (one block), its parts timed (the same arithmetic as ``Solver.step``)."""
    pt = time.process_time
    s.opt.zero_grad()
    t0 = pt()
    depth, T_w_c = s._depth(), s.poses()
    t1 = pt()
    idx = s._sample(gen)
    total = s._thread_loss(s.blocks[0], depth, T_w_c, idx)
    t2 = pt()
    total = s._add_regularisers(total, depth)
    t3 = pt()
    total.backward()
    t4 = pt()
    s.opt.step()
    t5 = pt()
    d = TOTALS.setdefault("by_weight" if s.points_by_weight else "uniform",
                          {**dict.fromkeys(PARTS, 0.0), "steps": 0, "points_per_step": s.points_per_step})
    for name, v in zip(PARTS, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
        d[name] += v
    d["steps"] += 1


def _split(min_pairs: int):
    original = S.run_solver

    def run_solver(solver, gen, steps, start, save):
        if len(solver.w.pairs) < min_pairs:
            return original(solver, gen, steps, start, save)
        for by_weight in (False, True, False, True):
            s = S.Solver(solver.w, solver.net, solver.posenet, solver.kf.lr, solver.depth, solver.losses, solver.kf,
                         1, by_weight)
            g = torch.Generator().manual_seed(0)
            for _ in range(6):
                _timed_step(s, g)
        out = {k: {**{p: round(1000 * d[p] / d["steps"], 1) for p in PARTS},
                   "step": round(1000 * sum(d[p] for p in PARTS) / d["steps"], 1),
                   "steps": d["steps"], "points_per_step": d["points_per_step"], "pairs": len(solver.w.pairs)}
               for k, d in TOTALS.items()}
        print(json.dumps(out))
        raise SystemExit(0)

    KF.run_solver = run_solver


def _curves(out: str) -> list[dict]:
    curves: list[dict] = []
    init, step = S.Solver.__init__, S.Solver.step

    def new_init(self, win, *a, **k):
        init(self, win, *a, **k)
        self._curve = {"frames": int(win.base.shape[0]), "pairs": len(win.pairs),
                       "trainable_poses": int(win.pose_train.sum()), "loss": []}
        curves.append(self._curve)

    def new_step(self, gen):
        loss = step(self, gen)
        self._curve["loss"].append(loss)
        return loss

    S.Solver.__init__, S.Solver.step = new_init, new_step
    return curves


def main() -> None:
    args = sys.argv[1:]
    if not args:
        raise SystemExit(__doc__)
    if args[0] == "--curves":
        out, args = args[1], args[2:]
        curves = _curves(out)
        code = cli.main(["run", *args])
        Path(out).write_text(json.dumps({"exit": code, "curves": curves}))
        return
    _split(290 if "--min-pairs" not in args else int(args[args.index("--min-pairs") + 1]))
    if "--min-pairs" in args:
        i = args.index("--min-pairs")
        args = args[:i] + args[i + 2:]
    cli.main(["run", *args, "--until", "optimize_keyframes", "--jobs", "1",
              "--set", "optimize_keyframes.pair_blocks=1"])


if __name__ == "__main__":
    main()
