"""``zagv record [-o DIR] [KEY ...]``: record the robot's topics as a rosbag2 folder with MCAP storage.

Standard ROS 2 types where one exists, ``zagv_msgs/msg/Message`` for the rest (``services/recorder/rosconv.py``).
Log times follow the robot's clock: the ``clock`` topic's time once one arrives (simulation), else wall time.
The latched ``map`` is fetched once at start. Prints a progress line (messages, MB, rate) once a second.
"""

from __future__ import annotations

import argparse
import contextlib
import queue
import sys
import time
from datetime import datetime
from pathlib import Path

import zenoh

from proto import codec
from proto.keys import split_key
from proto.messages import Clock
from proto.registry import TOPICS
from services.cli.common import add_client_options, client_keys, client_session


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", help="record topics to a rosbag2/MCAP bag (ROS 2 tools, Foxglove open it)")
    add_client_options(p)
    p.add_argument("keys", nargs="*", metavar="KEY", help="topic names or key expressions (default: every topic)")
    p.add_argument("-o", "--output", help="bag folder to create (default: zagv_<date>_<time>)")
    p.add_argument("--split-size-mb", type=float, default=0.0, help="start a new bag past this many MB (0: never)")
    p.add_argument("--split-duration", type=float, default=0.0, help="start a new bag every S s of log time (0: never)")
    p.add_argument("--duration", type=float, default=0.0, help="stop after S s of log time (0: until Ctrl-C)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    p.set_defaults(func=run_record)


class LogClock:
    """The robot's time for log stamps: the last ``clock`` message's stamp once one arrived, else wall time."""

    def __init__(self) -> None:
        self.sim_s: float | None = None

    def on_clock(self, msg: Clock) -> None:
        if self.sim_s is None or msg.stamp >= self.sim_s or msg.stamp < self.sim_s - 1.0:
            self.sim_s = msg.stamp

    def now_ns(self) -> int:
        return int(round((self.sim_s if self.sim_s is not None else time.time()) * 1e9))


def selected_names(keys: list[str]) -> list[str] | None:
    """Topic names to record from the KEY arguments (None: every registered topic)."""
    if not keys:
        return None
    names = []
    for k in keys:
        name = split_key(k)[1] if k.startswith("agv/") else k
        if name not in TOPICS:
            raise SystemExit(f"zagv record: unknown topic {k!r}; known: {', '.join(sorted(TOPICS))}")
        names.append(name)
    return names


def run_record(args: argparse.Namespace) -> int:
    from services.recorder.bag import BagRecorder

    keys = client_keys(args)
    names = selected_names(args.keys)
    out = Path(args.output or datetime.now().strftime("zagv_%Y%m%d_%H%M%S"))
    try:
        recorder = BagRecorder(out, robot_id=keys.robot_id, split_bytes=int(args.split_size_mb * 1e6),
                               split_duration_s=args.split_duration)
    except FileExistsError as exc:
        print(f"zagv record: {exc}", file=sys.stderr)
        return 2
    samples: queue.Queue[tuple[str, bytes, int]] = queue.Queue()
    clock = LogClock()
    clock_key = keys("clock")

    def on_sample(sample: zenoh.Sample) -> None:
        # stamped on arrival: a recorder that falls behind still logs each message at the time it was published
        key, payload = str(sample.key_expr), sample.payload.to_bytes()
        if key == clock_key:
            with contextlib.suppress(codec.ProtoDecodeError):
                clock.on_clock(codec.decode_as(Clock, payload, key))
        samples.put((key, payload, clock.now_ns()))

    session = client_session(args)
    subs = []
    bad: dict[str, int] = {}

    def write(key: str, payload: bytes, log_ns: int) -> None:
        name = split_key(key)[1]
        if name not in TOPICS or (names is not None and name not in names):
            return
        try:
            msg = codec.decode(name, payload)
        except codec.ProtoDecodeError as exc:
            bad[name] = bad.get(name, 0) + 1
            if bad[name] == 1:
                print(f"zagv record: skipping bad payloads on {name}: {exc}", file=sys.stderr)
            return
        recorder.write(name, msg, log_ns)

    try:
        if names is None:
            subs.append(session.declare_subscriber(keys.everything, on_sample))
        else:
            subs += [session.declare_subscriber(keys(n), on_sample) for n in dict.fromkeys([*names, "clock"])]
        if names is None or "map" in names:
            session.get(keys("map"), lambda r: r.ok is not None and on_sample(r.ok), timeout=2.0)
        next_line = time.monotonic() + 1.0
        while True:
            with contextlib.suppress(queue.Empty):
                write(*samples.get(timeout=0.2))
            if not args.quiet and time.monotonic() >= next_line:
                next_line += 1.0
                print(f"\rzagv record: {recorder.stats.line()}", end="", flush=True)
            if args.duration and recorder.stats.duration_s >= args.duration:
                break
    except KeyboardInterrupt:
        pass
    finally:
        for s in subs:
            s.undeclare()
        session.close()
        while True:  # what arrived before the stop is written
            try:
                write(*samples.get_nowait())
            except queue.Empty:
                break
        bags = recorder.close()
        print(f"\rzagv record: {recorder.stats.line()}")
        for bag in bags:
            print(f"zagv record: wrote {bag}")
    return 0

