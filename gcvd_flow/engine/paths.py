"""Where the cache lives (stdlib only: imported on the fast no-op path)."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """``$GCVD_FLOW_CACHE``, else the platform's user cache directory."""
    env = os.environ.get("GCVD_FLOW_CACHE")
    if env:
        return Path(env)
    import platformdirs

    return Path(platformdirs.user_cache_dir("gcvd-flow"))
