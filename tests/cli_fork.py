"""`gcvd-flow ARGS` in a process forked from a warm parent, for tests/conftest.py's ``cli``.

A fresh ``python -m gcvd_flow run`` spends ~5.5 s before its first stage: importing torch, OpenCV,
gtsam and the package, fingerprinting the stages. The suite starts ~300 such processes. Here each pytest worker starts one
server process (``python cli_fork.py``) that imports them once (``preload``); every command is a
child forked from it: a new process (its own exit code, stdout, stderr, signals, environment,
working directory, atexit handlers), minus the imports. The server runs nothing but imports, so
the fork copies no thread (OpenMP's pool, which breaks under fork, is never started there).

What a forked child cannot change, because the imports already read it: variables that the
interpreter or a numeric library read at start (PYTHON*, OMP_*, ...); ``conftest.cli`` runs a
real interpreter for those (``FRESH_ENV_PREFIXES``) and when a test asks (``fresh=True``).

Protocol: the server's first line is {"defaults": {variable: value}} (what its imports set by
default); then, one command at a time, the client writes one JSON line {args, env, cwd, stdout,
stderr} (the last two: file paths); the server answers {"pid": N} when the child runs, then
{"returncode": R} when it ends (R < 0: killed by signal -R, as subprocess reports it)."""

from __future__ import annotations

import importlib
import json
import os
import pkgutil
import sys

# environment variables read when the interpreter or a library starts, not when a command runs
FRESH_ENV_PREFIXES = ("PYTHON", "OMP_", "MKL_", "OPENBLAS_", "KMP_", "GOTO", "TORCH", "LD_", "CUDA", "OPENCV_")


def preload() -> None:
    """Import the package (every module but ``__main__``) and the numeric libraries its commands
    use. An import that fails here fails again, with its message, in the command that needs it."""
    from gcvd_flow.runtime import quiet_openmp

    quiet_openmp()  # as gcvd_flow.cli.main does before anything imports torch or OpenCV
    for name in ("torch", "cv2", "gtsam", "threadpoolctl"):  # threadpoolctl sets KMP_DUPLICATE_LIB_OK on import
        try:
            importlib.import_module(name)
        except ImportError:
            pass
    import gcvd_flow

    for m in pkgutil.walk_packages(gcvd_flow.__path__, "gcvd_flow."):
        if not m.name.endswith("__main__"):
            try:
                importlib.import_module(m.name)
            except Exception:  # noqa: BLE001 - the command that imports it reports it
                pass
    _fingerprint_stages()


def _fingerprint_stages() -> None:
    """The installed pipelines' stage fingerprints and numeric environment, memoised here once
    (~1 s per command otherwise). Safe because no test edits the package's own code between
    commands (tests that edit code fingerprint copies, in-process, with keys.clear_caches)."""
    from gcvd_flow.engine import api, keys

    for name in sorted(api.registered_pipelines()):
        try:
            pipeline = api.load_spec(name).pipeline
        except Exception:  # noqa: BLE001 - the command that loads it reports it
            continue
        pipeline.numeric_env()
        for stage in pipeline.stages:
            for fn in (stage.fn, *stage.resources.values()):
                keys.code_fingerprint(fn, pipeline.packages, pipeline.adapters)


def _child(req: dict, server_fd: int) -> int:
    """In the forked child: ``python -m gcvd_flow ARGS`` as the interpreter would run it; its exit
    code. ``server_fd``: the server's answer pipe, closed here (a child's own children would hold it)."""
    import atexit
    import runpy
    import tempfile
    import threading

    os.close(server_fd)
    os.environ.clear()
    os.environ.update(req["env"])
    os.chdir(req["cwd"])
    tempfile.tempdir = None  # re-read TMPDIR from this environment
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    for fd, path in ((1, req["stdout"]), (2, req["stderr"])):
        f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.dup2(f, fd)  # sys.stdout / sys.stderr write to fds 1 and 2
        os.close(f)
    sys.argv = ["gcvd_flow", *req["args"]]
    code = 0
    try:
        runpy.run_module("gcvd_flow", run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        if exc.code is None:
            code = 0
        elif isinstance(exc.code, int):
            code = exc.code
        else:
            print(exc.code, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: BLE001 - as the interpreter: the traceback, exit code 1
        sys.excepthook(*sys.exc_info())
        code = 1
    threading._shutdown()  # type: ignore[attr-defined]  # the interpreter joins threads, then atexit
    atexit._run_exitfuncs()
    for s in (sys.stdout, sys.stderr):
        try:
            s.flush()
        except Exception:  # noqa: BLE001
            pass
    return code & 0xFF


def serve() -> None:
    """The server's loop; its first line names the environment variables the imports set by
    default (``os.environ.setdefault``: a fresh command sets them too)."""
    start = dict(os.environ)
    preload()
    out = os.fdopen(os.dup(1), "w")
    out.write(json.dumps({"defaults": {k: v for k, v in os.environ.items() if k not in start}}) + "\n")
    out.flush()
    for line in sys.stdin:
        req = json.loads(line)
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                code = _child(req, out.fileno())
            finally:
                os._exit(code)
        out.write(json.dumps({"pid": pid}) + "\n")
        out.flush()
        _, status = os.waitpid(pid, 0)
        out.write(json.dumps({"returncode": os.waitstatus_to_exitcode(status)}) + "\n")
        out.flush()


if __name__ == "__main__":
    serve()
