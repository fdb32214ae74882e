"""``zagv goal X Y THETA``: send a navigation goal (map frame, m and rad) and follow it to its end.

Prints the reply (accepted with the goal id, or the reason for rejection), then the state changes from
``nav/status`` until the goal succeeds, fails or is canceled (``--no-wait`` returns after the reply; Ctrl-C cancels
the goal). Exit code 0 on success, 1 on failure or rejection.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import sys

from proto import codec
from proto import messages as m
from services.client.connect import client_keys, client_session
from services.common.query import QueryError, query

TERMINAL = ("succeeded", "failed", "canceled")


async def follow(args: argparse.Namespace) -> int:
    session = client_session(args)
    keys = client_keys(args)
    loop = asyncio.get_running_loop()
    statuses: asyncio.Queue[m.NavStatus] = asyncio.Queue()

    def on_status(sample) -> None:
        with contextlib.suppress(codec.ProtoDecodeError):
            msg = codec.decode_as(m.NavStatus, sample.payload.to_bytes(), str(sample.key_expr))
            loop.call_soon_threadsafe(statuses.put_nowait, msg)

    sub = session.declare_subscriber(keys("nav/status"), on_status)
    goal_id = ""
    try:
        if not all(math.isfinite(v) for v in (args.x, args.y, args.theta)):
            print("zagv goal: x, y and theta must be finite numbers", file=sys.stderr)
            return 2
        req = m.GoalRequest(pose=m.Pose2D(x=args.x, y=args.y, theta=args.theta), id=args.id)
        try:
            reply: m.GoalReply = await query(session, keys, "nav/goal", req, timeout_s=args.accept_timeout)
        except QueryError as exc:
            print(f"zagv goal: {exc} (is nav running?)", file=sys.stderr)
            return 1
        if not reply.accepted:
            print(f"zagv goal: rejected: {reply.reason}")
            return 1
        goal_id = reply.goal_id
        print(f"zagv goal: accepted as {goal_id}", flush=True)
        if args.no_wait:
            return 0
        deadline = loop.time() + args.timeout if args.timeout > 0 else math.inf
        last = ""
        while True:
            try:
                st = await asyncio.wait_for(statuses.get(), timeout=max(0.1, min(5.0, deadline - loop.time())))
            except TimeoutError:
                if loop.time() >= deadline:
                    await query(session, keys, "nav/cancel", m.CancelRequest(goal_id=goal_id))
                    print(f"zagv goal: timed out after {args.timeout:.0f} s; canceled")
                    return 1
                continue
            if st.goal_id != goal_id:
                continue
            line = f"{st.state}" + (f" ({st.distance_left_m:.2f} m left)" if st.state not in TERMINAL else "")
            if st.state != last:
                print(f"zagv goal: {line}" + (f": {st.error}" if st.error else ""), flush=True)
                last = st.state
            if st.state in TERMINAL:
                return 0 if st.state == "succeeded" else 1
    except asyncio.CancelledError:
        if goal_id:
            with contextlib.suppress(QueryError):
                await query(session, keys, "nav/cancel", m.CancelRequest(goal_id=goal_id))
        raise
    finally:
        sub.undeclare()
        session.close()


def run(args: argparse.Namespace) -> int:
    try:
        return asyncio.run(follow(args))
    except KeyboardInterrupt:
        return 130
