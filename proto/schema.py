"""JSON Schema of every message type, for non-Python clients.

``python -m proto.schema`` rewrites ``proto/schema/``; ``python -m proto.schema --check`` fails on drift.
Bytes fields are msgpack ``bin`` on the wire (base64 strings in JSON Schema terms); their numpy dtype and
column count are recorded under ``x-array``.
"""

from __future__ import annotations

import inspect
import json
import sys
from pathlib import Path

import msgspec

from proto.registry import QUERIES, TOPICS, all_types

SCHEMA_DIR = Path(__file__).with_name("schema")


def build() -> dict[str, str]:
    """File name -> JSON text for every schema file."""
    types = all_types()
    _, components = msgspec.json.schema_components(types, ref_template="#/$defs/{name}")
    for component in components.values():
        # docstrings as ``inspect.cleandoc`` gives them: msgspec 0.23 dedents them, earlier releases did not
        if "description" in component:
            component["description"] = inspect.cleandoc(component["description"])
    for t in types:
        if t.ARRAY_FIELDS and t.__name__ in components:
            for field, (dtype, cols) in t.ARRAY_FIELDS.items():
                prop = components[t.__name__]["properties"][field]
                prop["x-array"] = {"dtype": dtype, "columns": cols}
    files = {}
    for t in types:
        doc = {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "$id": f"zagv/{t.__name__}.json",
            "$ref": f"#/$defs/{t.__name__}",
            "$defs": components,
        }
        files[f"{t.__name__}.json"] = json.dumps(doc, indent=2, sort_keys=True) + "\n"
    index = {
        "topics": {k: v.__name__ for k, v in sorted(TOPICS.items())},
        "queries": {k: {"request": a.__name__, "reply": b.__name__} for k, (a, b) in sorted(QUERIES.items())},
        "key_prefix": "agv/<robot_id>/",
        "encoding": "msgpack (maps with field names)",
    }
    files["index.json"] = json.dumps(index, indent=2, sort_keys=True) + "\n"
    return files


def drift() -> list[str]:
    """Names of schema files that differ from the Structs (missing, changed or stale)."""
    want = build()
    have = {p.name for p in SCHEMA_DIR.glob("*.json")}
    bad = [n for n, text in want.items() if not (SCHEMA_DIR / n).exists() or (SCHEMA_DIR / n).read_text() != text]
    bad += sorted(have - set(want))
    return bad


def write() -> None:
    SCHEMA_DIR.mkdir(exist_ok=True)
    want = build()
    for p in SCHEMA_DIR.glob("*.json"):
        if p.name not in want:
            p.unlink()
    for name, text in want.items():
        (SCHEMA_DIR / name).write_text(text)


if __name__ == "__main__":
    if "--check" in sys.argv:
        stale = drift()
        if stale:
            print("schema drift in: " + ", ".join(stale) + " (run: python -m proto.schema)")
            sys.exit(1)
    else:
        write()
