"""Reading model weights files: the one place where weights come off the disk.

``.safetensors`` files are read as tensors only (a header over 100 MB is refused before it is
parsed); ``.pt`` / ``.pth`` with ``torch.load(weights_only=True)``, which refuses any pickle that
would build something other than tensors and plain containers. The state dict then goes to
``stages.models.load_model`` (architecture + strict key/shape check, no file access). Every
problem — missing file, refused pickle, corrupt or hostile file, weights of another model — is
a one-line :class:`WeightsError` (exit 2) naming the file.
"""

from __future__ import annotations

import json
import struct
import warnings
from pathlib import Path
from typing import Any

from gcvd_flow.engine.errors import UsageError

MAX_SAFETENSORS_HEADER = 100 << 20  # bytes; real headers are KBs, a hostile one can claim TBs


class WeightsError(UsageError):
    """A weights file that cannot be used (reported as one line, exit code 2)."""


def _safetensors_header_ok(path: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8:
            raise WeightsError(f"{path}: not a safetensors file (shorter than its header size)")
        (n,) = struct.unpack("<Q", head)
        size = path.stat().st_size
        if n > MAX_SAFETENSORS_HEADER or n > size - 8:
            raise WeightsError(f"{path}: safetensors header claims {n} bytes (file has {size}); refusing it")
        try:
            json.loads(f.read(n))
        except (UnicodeDecodeError, ValueError):
            raise WeightsError(f"{path}: safetensors header is not valid JSON") from None


def read_state_dict(path: str | Path) -> dict[str, Any]:
    """name -> torch.Tensor of a weights file; a ``module.`` prefix (DataParallel) is stripped
    and a checkpoint wrapping the weights under ``state_dict`` / ``model`` is unwrapped."""
    import pickle

    import torch

    p = Path(path).expanduser()
    if not p.is_file():
        raise WeightsError(f"{p}: weights file not found" if not p.exists() else f"{p}: not a regular file")
    state: Any
    try:
        if p.suffix == ".safetensors":
            from safetensors import SafetensorError
            from safetensors.torch import load_file

            _safetensors_header_ok(p)
            try:
                state = load_file(str(p), device="cpu")
            except SafetensorError as exc:
                raise WeightsError(f"{p}: not a valid safetensors file ({exc})") from None
        else:
            try:
                with warnings.catch_warnings():  # torch warns about pickle protocols on stderr
                    warnings.simplefilter("ignore")
                    state = torch.load(str(p), map_location="cpu", weights_only=True)
            except pickle.UnpicklingError as exc:
                why = next((ln.strip() for ln in str(exc).splitlines() if "Unsupported" in ln), "not tensors")
                raise WeightsError(f"{p}: refused to unpickle: only tensors are allowed ({why[:120]})") from None
            except (MemoryError, RecursionError) as exc:
                raise WeightsError(f"{p}: not a readable torch weights file ({type(exc).__name__})") from None
            except Exception as exc:  # noqa: BLE001 - any failure parsing a hostile file is the file's
                # (a garbage file made torch.load raise KeyError, IndexError, struct.error, ...)
                raise WeightsError(f"{p}: not a readable torch weights file ({type(exc).__name__})") from None
    except OSError as exc:
        raise WeightsError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if isinstance(state, dict):
        for key in ("state_dict", "model"):  # training checkpoints: {"model", "optimizer"}
            if key in state and isinstance(state[key], dict):
                state = state[key]
                break
    if not isinstance(state, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor)
                                              for k, v in state.items()):
        raise WeightsError(f"{p}: expected a state dict of named tensors, got {type(state).__name__}")
    return {(k[len("module."):] if k.startswith("module.") else k): v for k, v in state.items()}


def open_model(name: str, path: str | Path | None, **options: Any) -> Any:
    """Read ``path`` and build the weights backend ``name`` (stages.models registry) from it
    (None: the section's check lets no backend that needs weights run without a file)."""
    from gcvd_flow.stages.models import load_model

    if path is None:
        raise WeightsError(f"{name}: no weights file given")

    state = read_state_dict(path)
    try:
        return load_model(name, state, source=str(Path(path).expanduser()), **options)
    except ValueError as exc:  # wrong architecture: missing / unexpected / mis-shaped keys
        raise WeightsError(str(exc).splitlines()[0]) from None
