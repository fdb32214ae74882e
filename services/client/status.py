"""``zagv status [--json]``: which services are alive (health tokens) and their counters."""

from __future__ import annotations

import argparse
import json

import msgspec
import zenoh

from services.client.connect import client_keys, client_session
from services.launch.up import SERVICES


def collect(session: zenoh.Session, robot_id: str, timeout_s: float) -> dict[str, dict]:
    """{service: {"healthy": bool, "stats": {...}}} for every known or alive service."""
    from proto.keys import Keys

    keys = Keys(robot_id)
    alive = set()
    for reply in session.liveliness().get(keys.health_all, timeout=timeout_s):
        if reply.ok is not None:
            alive.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
    stats: dict[str, dict] = {}
    # every service answers, several of them from one process when composed (QueryTarget.ALL)
    for reply in session.get(keys("@stats/*"), target=zenoh.QueryTarget.ALL, timeout=timeout_s):
        if reply.ok is not None:
            name = str(reply.ok.key_expr).rsplit("/", 1)[-1]
            try:
                stats[name] = msgspec.json.decode(reply.ok.payload.to_bytes())
            except msgspec.DecodeError:
                stats[name] = {"error": "unreadable stats"}
    names = sorted(set(SERVICES) | alive | set(stats))
    return {n: {"healthy": n in alive, "stats": stats.get(n, {})} for n in names}


def run(args: argparse.Namespace) -> int:
    session = client_session(args)
    try:
        report = collect(session, client_keys(args).robot_id, args.timeout)
    finally:
        session.close()
    if args.json:
        print(json.dumps({"robot_id": args.robot_id, "services": report}, indent=2))
    else:
        for name, info in report.items():
            st = info["stats"]
            extra = f"up {st['uptime_s']:.0f} s" if "uptime_s" in st else ""
            bad = sum(st.get("bad_payloads", {}).values()) if st else 0
            if bad:
                extra += f", {bad} bad payloads"
            print(f"{name:<14} {'healthy' if info['healthy'] else 'DOWN':<8} {extra}")
    return 0 if any(i["healthy"] for i in report.values()) else 1
