"""gcvd-flow: globally consistent video depth and camera poses (GCVD) as a stage-cached DAG.

``gcvd_flow.engine`` is the workflow engine (knows no vision); the rest of the package is the
product: ``pipeline`` (the GCVD DAG), ``io``, ``exports``, ``evaluate``, ``cli``, ``api``.
Importing the package changes nothing in the process: the product's entry points apply its
process settings (``gcvd_flow.runtime``).
"""

__version__ = "0.1.0"
