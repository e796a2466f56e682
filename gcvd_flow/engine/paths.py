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


def is_cache_dir(path: str | Path) -> bool:
    """Whether ``path`` is a cache directory (has objects/ and records/): a path some run.json
    names is used as a cache only then, never created or filled in."""
    p = Path(path).expanduser()
    return (p / "objects").is_dir() and (p / "records").is_dir()
