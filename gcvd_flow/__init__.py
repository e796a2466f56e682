"""gcvd-flow: globally consistent video depth and camera poses (GCVD) as a stage-cached DAG.

``gcvd_flow.engine`` is the workflow engine (knows no vision); the rest of the package is the
product: ``pipeline`` (the GCVD DAG), ``io``, ``exports``, ``evaluate``, ``cli``, ``api``.
"""

import os as _os

# Idle OpenMP threads of the numeric libraries (torch's intra-op pool, OpenCV) sleep instead of
# spinning: two runs sharing cores otherwise burn each other's time slices busy-waiting (runs
# beside other jobs took 10-15x their time alone). Thread counts, and so results, are unchanged.
# Set before torch / OpenCV load their OpenMP runtime; a user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
