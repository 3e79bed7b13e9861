"""REP-2016 type hashes, version RIHS01: SHA-256 of a fixed JSON rendering of a description.

The rendering follows the reference implementation (rosidl_generator_type_description,
`calculate_type_hash`): `{"type_description": T, "referenced_type_descriptions": [...]}`
with every type referenced from T, directly or not, sorted by name; each type as
`{"type_name", "fields": [{"name", "type": {"type_id", "capacity", "string_capacity",
"nested_type_name"}}]}` in that key order (default values removed); `json.dumps` with
`separators=(", ", ": ")`, ASCII only, no indentation. The string form is `RIHS01_` and
the 64 lowercase hex digits of the digest.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from functools import cache
from typing import Any

from services.frontends.rosmsg.defs import BY_NAME, TypeDef

RIHS01_PREFIX = "RIHS01_"


def _individual(t: TypeDef) -> dict[str, Any]:
    return {
        "type_name": t.name,
        "fields": [
            {
                "name": f.name,
                "type": {
                    "type_id": f.type_id,
                    "capacity": f.capacity,
                    "string_capacity": f.string_capacity,
                    "nested_type_name": f.nested_type_name,
                },
            }
            for f in t.fields
        ],
    }


def referenced(t: TypeDef, types: Mapping[str, TypeDef] = BY_NAME) -> list[TypeDef]:
    """Every type `t` refers to, directly or through others, sorted by name."""
    seen: set[str] = set()
    queue = [f.nested_type_name for f in t.fields if f.nested_type_name]
    while queue:
        name = queue.pop()
        if name not in seen:
            seen.add(name)
            queue.extend(f.nested_type_name for f in types[name].fields if f.nested_type_name)
    return [types[name] for name in sorted(seen)]


def hashable_json(t: TypeDef, types: Mapping[str, TypeDef] = BY_NAME) -> str:
    """The exact text RIHS01 hashes for `t`."""
    doc = {
        "type_description": _individual(t),
        "referenced_type_descriptions": [_individual(r) for r in referenced(t, types)],
    }
    return json.dumps(doc, ensure_ascii=True, allow_nan=False, separators=(", ", ": "))


@cache
def rihs01(type_name: str) -> str:
    """`RIHS01_<sha256 hex>` of one of our types, by its `pkg/msg/Name`."""
    digest = hashlib.sha256(hashable_json(BY_NAME[type_name]).encode("utf-8")).hexdigest()
    return RIHS01_PREFIX + digest
