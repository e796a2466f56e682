"""JSON Schemas of the GCVD artifact kinds (one ``<kind>.json`` each). The engine's own schemas
(map stages, checkpoints, the shared ``common.json`` these $ref) are in gcvd_flow/engine/schemas/."""

from pathlib import Path

SCHEMA_DIR = Path(__file__).resolve().parent
