"""gcvd-flow: the stage-cached DAG engine and the product shell (knows nothing about vision)."""

__version__ = "0.1.0"
