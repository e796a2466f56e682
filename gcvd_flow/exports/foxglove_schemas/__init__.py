"""Foxglove's JSON schemas, vendored verbatim (not retyped) from the upstream files:

    repository  https://github.com/foxglove/foxglove-sdk
    commit      ca8a1ced73b2737d03e2e3f282b57359a1a4cb72 (2026-08-17)
    path        schemas/jsonschema/<Name>.json  ->  here foxglove.<Name>.json
    licence     MIT, Copyright (c) Foxglove Technologies Inc (LICENSE beside these files)

Neither the ``mcap`` pip package nor a foxglove package in this environment ships the JSON
files. To update: copy the files of a newer commit over these, unchanged, and change the commit
above. ``schema_bytes(name)`` returns a file's bytes as they are (what run.mcap embeds).
"""

from __future__ import annotations

from importlib import resources

NAMES = ("foxglove.RawImage", "foxglove.CompressedImage", "foxglove.CameraCalibration", "foxglove.FrameTransform",
         "foxglove.PosesInFrame", "foxglove.PointCloud")


def schema_bytes(name: str) -> bytes:
    """The upstream JSON schema file of ``name`` (e.g. "foxglove.RawImage"), byte for byte."""
    if name not in NAMES:
        raise KeyError(f"no vendored foxglove schema {name!r}")
    return (resources.files(__name__) / f"{name}.json").read_bytes()
