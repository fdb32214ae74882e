"""``zagv record [-o DIR] [KEY ...]``: record the robot's topics as a rosbag2 folder with MCAP storage (the
command's arguments: services/cli/record.py).

Standard ROS 2 types where one exists, ``zagv_msgs/msg/Message`` for the rest (``services/recorder/rosconv.py``).
Log times follow the robot's clock: the ``clock`` topic's time once one arrives (simulation), else wall time.
The latched ``map`` is fetched once at start. Prints a progress line (messages, MB, rate) once a second.

Nothing is lost to a busy writer: one subscriber on the robot's keys delivers into Zenoh's own FIFO channel
(``CHANNEL_CAPACITY`` samples), which Zenoh's receive thread fills without Python's interpreter lock, so a writer
thread busy converting and compressing (or starved on a loaded machine) never stops the socket from being read; with
a Python callback it did, the router's queue towards the recorder filled and the router dropped scans (32 of 12283
at a load of 11). A thread moves the samples on, stamped in arrival order, into the writer's queue, which holds at
most ``MAX_BACKLOG_BYTES`` of payload: past that, samples are dropped and counted per topic (progress line and
final report), never silently.
"""

from __future__ import annotations

import collections
import contextlib
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import zenoh

from proto import codec
from proto.keys import Keys, split_key
from proto.messages import Clock
from proto.registry import TOPICS
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.recorder.bag import BagRecorder

#: samples Zenoh's receive thread may hold for the recorder before it waits (minutes of every topic at 1x)
CHANNEL_CAPACITY = 65536
#: payload bytes waiting for the writer before new samples are dropped (and counted)
MAX_BACKLOG_BYTES = 512 * 1024 * 1024

#: (key, payload, sim ns or None, wall ns) of one received sample
Arrival = tuple[str, bytes, int | None, int]


class Backlog:
    """Samples received and not yet written, in arrival order: at most ``max_bytes`` of payload; a sample that does
    not fit is dropped and counted per topic (``dropped``)."""

    def __init__(self, max_bytes: int = MAX_BACKLOG_BYTES) -> None:
        self.max_bytes = max_bytes
        self.queue: queue.Queue[Arrival] = queue.Queue()
        self.lock = threading.Lock()
        self.held_bytes = 0
        self.dropped: collections.Counter[str] = collections.Counter()

    def put(self, item: Arrival) -> bool:
        """Hold ``item`` for the writer; False (and counted) when the backlog is full."""
        size = len(item[1])
        with self.lock:
            if self.held_bytes + size > self.max_bytes:
                self.dropped[split_key(item[0])[1]] += 1
                return False
            self.held_bytes += size
        self.queue.put(item)
        return True

    def get(self, timeout_s: float | None = None) -> Arrival:
        """The oldest held sample (``queue.Empty`` when none came within ``timeout_s``; None: do not wait)."""
        item = self.queue.get(timeout=timeout_s) if timeout_s is not None else self.queue.get_nowait()
        with self.lock:
            self.held_bytes -= len(item[1])
        return item

    def drop_line(self) -> str:
        """"" (nothing dropped) or how many samples were dropped, per topic."""
        if not self.dropped:
            return ""
        per_topic = ", ".join(f"{n} {t}" for t, n in sorted(self.dropped.items()))
        return f"dropped {sum(self.dropped.values())} message(s) past a {self.max_bytes / 1e6:.0f} MB backlog " \
               f"({per_topic})"


def _drain(receiver: Any, arrive: Callable[[zenoh.Sample], None]) -> None:
    """Move samples from Zenoh's channel to ``arrive`` until the subscriber is undeclared (the channel closes)."""
    while True:
        try:
            sample = receiver.recv()  # waits without the interpreter lock
        except zenoh.ZError:  # closed and empty
            return
        arrive(sample)


class LogClock:
    """The robot's time for log stamps: the last ``clock`` message's stamp once one arrived, else wall time.

    The time base is chosen once: the clock's when a ``clock`` message comes within ``WAIT_S`` of the start (messages
    that arrived before it, such as the latched map, get its time), else wall time for the whole recording, so a bag
    never mixes the two. The start is when the subscriptions exist (``subscribed``): opening the session can take
    longer than ``WAIT_S`` on a loaded machine, which then recorded a simulated run on wall time."""

    WAIT_S = 2.0

    def __init__(self) -> None:
        self.sim_s: float | None = None
        self.first_sim_s: float | None = None
        self.sim_base: bool | None = None
        self.started: float | None = None  # set by ``subscribed``

    def subscribed(self) -> None:
        """The subscriptions exist: the wait for a first ``clock`` starts now."""
        self.started = time.monotonic()

    def on_clock(self, msg: Clock) -> None:
        if self.sim_s is None or msg.stamp >= self.sim_s or msg.stamp < self.sim_s - 1.0:
            self.sim_s = msg.stamp
            if self.first_sim_s is None:
                self.first_sim_s = msg.stamp
                self.sim_base = self.started is None or time.monotonic() - self.started <= self.WAIT_S

    def arrival(self) -> tuple[int | None, int]:
        """(sim ns or None, wall ns) of a message arriving now."""
        return (None if self.sim_s is None else int(round(self.sim_s * 1e9))), time.time_ns()

    def decide_now(self) -> None:
        """No more waiting: wall time unless a clock came."""
        if self.sim_base is None:
            self.sim_base = False

    def log_ns(self, sim_ns: int | None, wall_ns: int) -> int | None:
        """The log time of a message that arrived at (sim_ns, wall_ns); None: not decided yet (wait)."""
        if self.sim_base is None and self.started is not None and time.monotonic() - self.started >= self.WAIT_S:
            self.sim_base = False
        if self.sim_base is None:
            return None
        if not self.sim_base:
            return wall_ns
        return sim_ns if sim_ns is not None else int(round((self.first_sim_s or 0.0) * 1e9))


class _Recording:
    """One ``zagv record`` run: samples arrive on Zenoh's side (``on_sample``), the main thread writes them
    (``write``) in arrival order, and ``finish`` writes what is still held and closes the bag."""

    def __init__(self, recorder: BagRecorder, keys: Keys, names: list[str] | None) -> None:
        self.recorder = recorder
        self.names = names
        self.samples = Backlog()
        self.pending: list[Arrival] = []
        self.clock = LogClock()
        self.clock_key = keys("clock")
        self.wanted = None if names is None else {*names, "clock"}
        self.bad: dict[str, int] = {}

    def on_sample(self, sample: zenoh.Sample) -> None:
        """Stamped on arrival, in arrival order: a writer that falls behind still logs each message at the clock time
        it arrived at."""
        key = str(sample.key_expr)
        if self.wanted is not None and split_key(key)[1] not in self.wanted:
            return
        payload = sample.payload.to_bytes()
        if key == self.clock_key:
            with contextlib.suppress(codec.ProtoDecodeError):
                self.clock.on_clock(codec.decode_as(Clock, payload, key))
        if not self.samples.put((key, payload, *self.clock.arrival())) and sum(self.samples.dropped.values()) == 1:
            print(f"\nzagv record: the writer is {self.samples.max_bytes / 1e6:.0f} MB behind: dropping messages "
                  f"(counted)", file=sys.stderr)

    def write(self, key: str, payload: bytes, sim_ns: int | None, wall_ns: int) -> None:
        """Decode and write one sample at its log time (held while the time base is undecided)."""
        log_ns = self.clock.log_ns(sim_ns, wall_ns)
        if log_ns is None:
            self.pending.append((key, payload, sim_ns, wall_ns))
            return
        while self.pending:
            self.write(*self.pending.pop(0))
        name = split_key(key)[1]
        if name not in TOPICS or (self.names is not None and name not in self.names):
            return
        try:
            msg = codec.decode(name, payload)
        except codec.ProtoDecodeError as exc:
            self.bad[name] = self.bad.get(name, 0) + 1
            if self.bad[name] == 1:
                print(f"zagv record: skipping bad payloads on {name}: {exc}", file=sys.stderr)
            return
        self.recorder.write(name, msg, log_ns)

    def write_until(self, duration_s: float, quiet: bool) -> None:
        """Write as samples come, with a progress line a second, until ``duration_s`` of log time (0: Ctrl-C)."""
        next_line = time.monotonic() + 1.0
        while True:
            with contextlib.suppress(queue.Empty):
                self.write(*self.samples.get(timeout_s=0.2))
            if not quiet and time.monotonic() >= next_line:
                next_line += 1.0
                drops = self.samples.drop_line()
                print(f"\rzagv record: {self.recorder.stats.line()}{'  ' + drops if drops else ''}", end="",
                      flush=True)
            if duration_s and self.recorder.stats.duration_s >= duration_s:
                return

    def finish(self) -> None:
        """Write what arrived before the stop, close the bag and report."""
        self.clock.decide_now()  # for what is still undecided
        while True:
            try:
                self.write(*self.samples.get())
            except queue.Empty:
                break
        while self.pending:
            self.write(*self.pending.pop(0))
        bags = self.recorder.close()
        print(f"\rzagv record: {self.recorder.stats.line()}")
        if drops := self.samples.drop_line():
            print(f"zagv record: {drops}", file=sys.stderr)
        for bag in bags:
            print(f"zagv record: wrote {bag}")


def record(settings: ZenohSettings, keys: Keys, output: str | None, names: list[str] | None, *,
           split_size_mb: float = 0.0, split_duration_s: float = 0.0, duration_s: float = 0.0,
           quiet: bool = False) -> int:
    """Record ``names`` (None: every topic) into the bag folder ``output`` (None: ``zagv_<date>_<time>``) until
    ``duration_s`` of log time (0: until Ctrl-C); the exit code of ``zagv record`` (2: the folder exists)."""
    if threading.current_thread() is threading.main_thread():
        # SIGINT ends the recording (the bag is closed), also when started from a script that ignores SIGINT for its
        # background jobs (`zagv record & ... kill -INT`): a process inherits the ignore, and Python sets no handler
        signal.signal(signal.SIGINT, signal.default_int_handler)
    out = Path(output or datetime.now().strftime("zagv_%Y%m%d_%H%M%S"))
    try:
        recorder = BagRecorder(out, robot_id=keys.robot_id, split_bytes=int(split_size_mb * 1e6),
                               split_duration_s=split_duration_s)
    except FileExistsError as exc:
        print(f"zagv record: {exc}", file=sys.stderr)
        return 2
    run = _Recording(recorder, keys, names)
    session = open_session(settings)
    # one subscriber (also for chosen topics, filtered on arrival), so that one channel keeps the order in which
    # `clock` and the other topics arrived
    sub = session.declare_subscriber(keys.everything, zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
    receiver = threading.Thread(target=_drain, args=(sub.handler, run.on_sample), name="zagv-record-receive",
                                daemon=True)
    receiver.start()
    try:
        run.clock.subscribed()
        if names is None or "map" in names:
            session.get(keys("map"), lambda r: run.on_sample(r.ok) if r.ok is not None else None, timeout=2.0)
        run.write_until(duration_s, quiet)
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        receiver.join(timeout=10.0)  # what Zenoh still held reaches the backlog
        session.close()
        run.finish()
    return 0
