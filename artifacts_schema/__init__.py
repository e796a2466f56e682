"""JSON Schemas of the artifact kinds (one ``<kind>.json`` each) and of the run manifest."""

from pathlib import Path

SCHEMA_DIR = Path(__file__).resolve().parent
