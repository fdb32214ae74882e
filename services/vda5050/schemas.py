"""The official VDA 5050 2.0 JSON schemas (``schemas/v2.0``, see ``schemas/README.md``) and a validator per topic.

``validate(topic, message)`` returns the violations as readable strings (empty: valid). The schemas reference
each other by their ``$id`` (``http://vda-5050-schema.org/v2.0/...``); a local registry resolves those, so nothing
is fetched.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

import jsonschema
from referencing import Registry, Resource

SCHEMA_DIR = Path(__file__).resolve().parent / "schemas" / "v2.0"

#: VDA 5050 topic -> schema file
TOPIC_SCHEMAS = {
    "order": "order.schema.json",
    "instantActions": "instant-actions.schema.json",
    "state": "state.schema.json",
    "visualization": "visualization.schema.json",
    "connection": "connection.schema.json",
    "factsheet": "factsheet.schema.json",
}


@cache
def _registry() -> Registry:
    resources = []
    for path in sorted(SCHEMA_DIR.glob("*.schema.json")):
        contents = json.loads(path.read_text(encoding="utf-8"))
        resources.append((contents["$id"], Resource.from_contents(contents)))
    return Registry().with_resources(resources)


@cache
def validator(topic: str) -> jsonschema.protocols.Validator:
    """The Draft 7 validator of ``topic``'s schema, with date-time format checking."""
    schema = json.loads((SCHEMA_DIR / TOPIC_SCHEMAS[topic]).read_text(encoding="utf-8"))
    cls = jsonschema.validators.validator_for(schema)
    return cls(schema, registry=_registry(), format_checker=cls.FORMAT_CHECKER)


def validate(topic: str, message: Any, limit: int = 3) -> list[str]:
    """Up to ``limit`` violations of ``message`` against ``topic``'s schema, each as ``path: reason``."""
    out = []
    for error in validator(topic).iter_errors(message):
        where = "/".join(str(p) for p in error.absolute_path) or "(root)"
        reason = error.message if len(error.message) <= 160 else error.message[:157] + "..."
        out.append(f"{where}: {reason}")
        if len(out) >= limit:
            break
    return out
