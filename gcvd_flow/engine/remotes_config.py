"""Named remotes: ``remotes.toml`` maps a name to an fsspec URL and its storage options.

::

    default = "team"                 # used when push / pull / run --push name no remote

    [remotes.team]
    url = "s3://lab-bucket/gcvd-cache"
    endpoint_url = "https://minio.lab.example:9000"   # any other key goes to fsspec as is

    [remotes.nas]
    url = "sftp://cache@nas.lab/srv/gcvd"

Where the file is: ``--remotes FILE``, else ``$GCVD_FLOW_REMOTES``, else
``platformdirs.user_config_dir("gcvd-flow")/remotes.toml``. Credentials do not belong here:
S3 reads them from the standard AWS environment and config (``AWS_ACCESS_KEY_ID``,
``AWS_PROFILE``, ``AWS_ENDPOINT_URL``, ``~/.aws/``), SFTP from ssh keys / the agent.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.names import ENV_REMOTES, TOOL

ENV_VAR = ENV_REMOTES
# options whose value is text for every fsspec backend (an endpoint_url = 12 failed deep in botocore)
_TEXT_OPTION = re.compile(r"(url|host|profile|key|secret|token|user|username|password|region|region_name)$")


@dataclass
class RemoteSpec:
    url: str
    options: dict[str, Any] = field(default_factory=dict)
    name: str | None = None

    @property
    def label(self) -> str:
        return f"{self.name} ({self.url})" if self.name else self.url


def config_path(explicit: str | None = None) -> Path:
    if explicit:
        return Path(explicit).expanduser()
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser()
    import platformdirs

    return Path(platformdirs.user_config_dir(TOOL)) / "remotes.toml"


def load(explicit: str | None = None) -> tuple[Path, dict[str, Any]]:
    """(path, parsed TOML); an absent file is an empty configuration unless named explicitly."""
    import tomllib

    path = config_path(explicit)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        if explicit:
            raise UsageError(f"{path}: remotes file not found") from None
        return path, {}
    except OSError as exc:
        raise UsageError(f"{path}: cannot read remotes file ({exc.strerror})") from None
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UsageError(f"{path}: not valid TOML ({exc})") from None
    remotes = doc.get("remotes", {})
    if not isinstance(remotes, dict) or not all(isinstance(v, dict) for v in remotes.values()):
        raise UsageError(f"{path}: [remotes.NAME] tables expected")
    return path, doc


def _looks_like_location(text: str) -> bool:
    return "://" in text or "/" in text or text.startswith((".", "~")) or os.path.exists(text)


def resolve(name_or_url: str | None, explicit_file: str | None = None) -> RemoteSpec:
    """A configured name, else a URL or path (``s3://b/p``, ``file:///x``, ``/x``, ``./x``).

    A bare word that is neither configured nor an existing path is an error rather than a new
    directory of that name (a typo in a remote's name must not create a local cache)."""
    path, doc = load(explicit_file)
    remotes = doc.get("remotes", {})
    if name_or_url is None:
        name_or_url = doc.get("default")
        if not isinstance(name_or_url, str):
            raise UsageError(f"no remote given: use --remote NAME|URL, or set default = \"NAME\" in {path}")
    entry = remotes.get(name_or_url)
    if entry is not None:
        opts = {k: v for k, v in entry.items() if k != "url"}
        for k, v in opts.items():
            if _TEXT_OPTION.search(k) and not isinstance(v, str):
                raise UsageError(f"{path}: [remotes.{name_or_url}] {k} must be a string, not {v!r}")
        url = entry.get("url")
        if not isinstance(url, str) or not url:
            raise UsageError(f"{path}: [remotes.{name_or_url}] has no url")
        return RemoteSpec(url, opts, name_or_url)
    if not _looks_like_location(name_or_url):
        known = ", ".join(sorted(remotes)) or "none"
        raise UsageError(f"unknown remote {name_or_url!r} (configured in {path}: {known}); "
                         f"for a directory write ./{name_or_url}")
    return RemoteSpec(name_or_url)
