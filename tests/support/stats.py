"""A service's counters, as ``zagv inspect`` shows them: the ``@stats/<service>`` queryable's JSON."""

from __future__ import annotations

import json
from typing import Any


def service_stats(stack: Any, service: str, timeout_s: float = 2.0) -> dict:
    """The JSON that ``@stats/<service>`` answers with, from a running test stack."""
    for reply in stack.session().get(stack.keys(f"@stats/{service}"), timeout=timeout_s):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    raise AssertionError(f"no stats from {service}")
