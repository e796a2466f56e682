"""Error kinds the CLI maps to exit codes (2 for the user's input, 1 for our bugs)."""


class UsageError(ValueError):
    """Bad usage or bad input: reported as one line on stderr, exit code 2."""


class StoreError(RuntimeError):
    """The cache cannot serve a request (missing or corrupt objects that could not be healed,
    a directory that is not a cache): reported as one line, exit code 2."""


class WorkerError(RuntimeError):
    """The processes computing map items were lost: a worker killed (out of memory?) again and
    again, the Dask scheduler gone. Reported as one line, exit code 2; what finished is in the
    cache, a re-run resumes."""
