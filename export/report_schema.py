"""The schema of an export's ``export_report.json``, checked before any stage reads it.

An export folder travels and anyone can edit it: the report is validated (JSON Schema, draft 2020-12) for
the types, ranges, lengths and characters of every field a later stage reads (the deployment report, the
regeneration of the C, HIL), so a number given as a string or markup in a digest is refused in one line
before anything is generated, built or rendered. Fields no stage reads are free.
"""

from __future__ import annotations

from typing import Any

from embedrl.export.target import TARGETS

HEX64 = {"type": "string", "pattern": "^[0-9a-f]{64}$"}
TEXT = {"type": "string", "maxLength": 8192, "pattern": "^[^\\x00-\\x1f\\x7f]*$"}
"""One line of text (a command, a path, a compiler version): no control characters, bounded."""
COUNT = {"type": "integer", "minimum": 0}
NUMBER = {"type": "number"}
RELATIVE_PATH = "^(?!/)(?!.*(^|/)\\.\\.(/|$))[A-Za-z0-9_./ -]{1,256}$"

EXPORT_REPORT: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "required": [
        "tool",
        "source",
        "name",
        "quantize",
        "env_id",
        "interface",
        "observation_dim",
        "action_dim",
        "ops",
        "compiler",
        "verification",
        "files",
    ],
    "properties": {
        "tool": {"type": "string", "pattern": "^embedrl [0-9A-Za-z.+_-]{1,64}$"},
        "source": {
            "type": "object",
            "required": ["path", "sha256"],
            "properties": {"path": TEXT, "sha256": HEX64, "kind": {"enum": ["sb3", "onnx"]}},
        },
        "name": {"type": "string", "pattern": "^[a-z][a-z0-9_]{0,30}$"},
        "quantize": {"enum": [None, "int8", "int8-weights", "q15"]},
        "env_id": {"type": "string", "pattern": "^([A-Za-z0-9][A-Za-z0-9_./-]{0,99})?$"},
        "interface": {"type": "object", "required": ["observation", "action"]},
        "observation_dim": {"type": "integer", "minimum": 1, "maximum": 1 << 20},
        "action_dim": {"type": "integer", "minimum": 1, "maximum": 1 << 20},
        "ops": {
            "type": "array",
            "maxItems": 100_000,
            "items": {"type": "string", "pattern": "^[A-Za-z0-9_]{1,40}$"},
        },
        "compiler": {
            "type": "object",
            "required": ["command"],
            "properties": {"command": TEXT, "version": TEXT},
        },
        "verification": {
            "type": "object",
            "required": ["tolerance"],
            "properties": {"tolerance": {"type": "number", "minimum": 0}, "samples": COUNT},
        },
        "targets": {
            "type": "object",
            "propertyNames": {"enum": sorted(TARGETS)},
            "additionalProperties": {
                "type": "object",
                "properties": {
                    "flash_bytes": COUNT,
                    "ram_bytes": COUNT,
                    "stack_bytes": COUNT,
                    "instructions_per_inference": NUMBER,
                    "estimated_cycles_per_inference": NUMBER,
                    "estimated_inference_us": NUMBER,
                },
            },
        },
        "files": {
            "type": "object",
            "propertyNames": {"pattern": RELATIVE_PATH},
            "additionalProperties": HEX64,
        },
    },
}


def check_export_report(data: Any) -> None:
    """ValueError, one line naming the first field that breaks :data:`EXPORT_REPORT`."""
    import jsonschema

    error = jsonschema.exceptions.best_match(jsonschema.Draft202012Validator(EXPORT_REPORT).iter_errors(data))
    if error is not None:
        where = "/".join(str(p) for p in error.absolute_path) or "the report"
        shown = repr(error.instance)[:60].encode("ascii", "backslashreplace").decode()
        raise ValueError(f"{where}: {shown} is not allowed ({error.validator} {error.validator_value!r:.80})")
