"""The engine's names, spelled once (stdlib only: imported on the fast no-op path): the tool's
name (command, distribution, user cache / config folder), its environment variables and the
entry-point group pipelines register under."""

TOOL = "gcvd-flow"  # the command, the installed distribution, the platformdirs app name
ENTRY_POINT_GROUP = "gcvd_flow.pipelines"  # pyproject.toml: [project.entry-points."gcvd_flow.pipelines"]

ENV_CACHE = "GCVD_FLOW_CACHE"  # default cache directory
ENV_JOBS = "GCVD_FLOW_JOBS"  # default number of worker processes
ENV_REMOTES = "GCVD_FLOW_REMOTES"  # default remotes file
ENV_FSYNC = "GCVD_FLOW_FSYNC"  # "always": fsync every object and record
ENV_OVERLAP = "GCVD_FLOW_OVERLAP"  # "1": run ready map stages beside a whole stage (runner._Beside)
