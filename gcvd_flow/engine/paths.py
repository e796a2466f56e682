"""Where the cache lives (stdlib only: imported on the fast no-op path)."""

from __future__ import annotations

import os
from pathlib import Path

from gcvd_flow.engine.names import ENV_CACHE, TOOL


def default_cache_dir() -> Path:
    """``$GCVD_FLOW_CACHE``, else the platform's user cache directory."""
    env = os.environ.get(ENV_CACHE)
    if env:
        return Path(env)
    import platformdirs

    return Path(platformdirs.user_cache_dir(TOOL))
