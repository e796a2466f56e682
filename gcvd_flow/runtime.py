"""Process settings of the product, applied by its entry points (``gcvd_flow.cli.main``, the
Python API ``gcvd_flow.api``) and at worker start-up (``gcvd_flow.pipeline.limit_threads``) —
never by importing the engine, which any pipeline may use.
"""

from __future__ import annotations

import os


def quiet_openmp() -> None:
    """Idle OpenMP threads of the numeric libraries (torch's intra-op pool, OpenCV) sleep instead
    of spinning: two runs sharing cores otherwise burn each other's time slices busy-waiting
    (runs beside other jobs took 10-15x their time alone). Thread counts, and so results, are
    unchanged. Takes effect in a process whose OpenMP runtime is not loaded yet (torch / OpenCV
    not imported) and in the processes it starts; a user's own setting wins."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
