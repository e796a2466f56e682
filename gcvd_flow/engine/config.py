"""Typed parameters: pydantic models per stage, TOML files, ``--set`` overrides, profiles.

Precedence (later wins): model defaults < named profile < ``--config`` file < ``--set``.
A config file may define its own profiles under ``[profiles.NAME]``. Every key is checked:
an unknown section or key, or a value of the wrong type, is a one-line error naming it.
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from gcvd_flow.engine.errors import UsageError
from gcvd_flow.engine.keys import digest_file, key_of


class Section(BaseModel):
    """Base of a stage's parameter model: unknown keys are errors; paths enter keys by content;
    ``inf`` / ``nan`` are no parameter value (a float field rejects them, naming the key).

    Fields whose ``json_schema_extra`` has ``{"file": True}`` name local files (model weights):
    their *content digest*, not their path, goes into the cache key, so that a teammate with
    the same weights elsewhere on disk shares the cache. ``{"dir": True}``: a folder (e.g. the
    user's masks): the names and content digests of its files.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    def key_dict(self) -> dict[str, Any]:
        out = self.model_dump(mode="python")
        for name, info in type(self).model_fields.items():
            extra = info.json_schema_extra if isinstance(info.json_schema_extra, dict) else {}
            if extra.get("file") and out.get(name):
                p = Path(out[name]).expanduser()
                if not p.is_file():
                    raise UsageError(f"{name}: file not found: {p}")
                out[name] = "blake3:" + digest_file(p)
            elif extra.get("dir") and out.get(name):  # a folder of files: their names and contents
                p = Path(out[name]).expanduser()
                if not p.is_dir():
                    raise UsageError(f"{name}: not a folder: {p}")
                out[name] = "blake3:" + key_of(sorted((f.name, digest_file(f)) for f in p.iterdir() if f.is_file()))
        return out


def _parse_value(text: str) -> Any:
    """A --set value as TOML (numbers, booleans, strings, arrays); bare words are strings."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def _deep_update(base: dict[str, Any], upd: dict[str, Any]) -> dict[str, Any]:
    for k, v in upd.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _deep_update(base[k], v)
        else:
            base[k] = v
    return base


def parse_set(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise UsageError(f"--set {item!r}: expected section.key=value")
        path, _, raw = item.partition("=")
        parts = [p.strip() for p in path.strip().split(".") if p.strip()]
        if not parts:
            raise UsageError(f"--set {item!r}: empty key")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise UsageError(f"--set {item!r}: {p} is not a section")
        node[parts[-1]] = _parse_value(raw.strip())
    return out


def load_toml(path: str | Path) -> dict[str, Any]:
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UsageError(f"config file not found: {p}") from None
    except IsADirectoryError:
        raise UsageError(f"config file {p} is a directory") from None
    except OSError as exc:
        raise UsageError(f"config file {p}: cannot read ({exc.strerror or exc})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UsageError(f"config file {p} is not valid TOML: {exc}") from None


def build_config(model: type[BaseModel], profiles: dict[str, dict[str, Any]],
                 profile: str | None = None, config_file: str | Path | None = None,
                 sets: list[str] | None = None) -> BaseModel:
    """Resolve defaults, profile, file and --set overrides into a validated model."""
    data: dict[str, Any] = {}
    file_data: dict[str, Any] = load_toml(config_file) if config_file else {}
    all_profiles = dict(profiles)
    all_profiles.update(file_data.pop("profiles", {}) or {})
    if profile:
        if profile not in all_profiles:
            raise UsageError(f"unknown profile {profile!r}; known: {', '.join(sorted(all_profiles)) or 'none'}")
        _deep_update(data, copy.deepcopy(all_profiles[profile]))
    _deep_update(data, file_data)
    _deep_update(data, parse_set(sets or []))
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        if err["type"] == "extra_forbidden":
            raise UsageError(f"unknown config key {loc!r}{_did_you_mean(model, loc)}") from None
        raise UsageError(f"config key {loc!r}: {err['msg']} (got {err.get('input')!r})") from None


def known_keys(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every dotted key of ``model``: sections and their parameters ("keyframes", "keyframes.delta")."""
    out: list[str] = []
    for name, info in model.model_fields.items():
        out.append(prefix + name)
        ann = info.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out.extend(known_keys(ann, prefix + name + "."))
    return out


def _did_you_mean(model: type[BaseModel], key: str) -> str:
    """"; did you mean 'keyframes.delta'?" for the closest known key (difflib), else ""."""
    import difflib

    keys = known_keys(model)
    last = key.rsplit(".", 1)[-1]
    # a real parameter name in the wrong section ("association.delta" -> "keyframes.delta")
    best = [k for k in keys if "." in k and k.rsplit(".", 1)[-1] == last and "." in key][:1]
    if not best:  # a typo: the closest key of the same depth
        same_depth = [k for k in keys if k.count(".") == key.count(".")]
        best = difflib.get_close_matches(key, same_depth, n=1, cutoff=0.6)
    return f"; did you mean {best[0]!r}?" if best else ""
