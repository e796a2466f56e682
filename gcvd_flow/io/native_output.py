"""Keep what native libraries print to the process's stdout off our stdout.

gtsam_unstable's inverse-depth factors print one line to C++ ``std::cout`` each time an
optimiser's trial step puts a landmark behind a camera (the step is then rejected; nothing is
wrong). Thousands of such lines would corrupt ``--json`` output, which is stdout, so the bundle
adjustment runs with file descriptor 1 pointed at /dev/null. Only the main thread runs whole
stages, and nothing of ours writes to stdout while one runs.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from typing import Iterator


@contextlib.contextmanager
def native_stdout_silenced() -> Iterator[None]:
    """Point fd 1 at /dev/null for the block; C stdio buffers are flushed on both edges so
    nothing printed before lands in /dev/null and nothing printed inside lands on stdout later."""
    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    libc.fflush(None)
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        sys.stdout.flush()
        libc.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)
