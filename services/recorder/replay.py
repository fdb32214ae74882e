"""``zagv replay PATH [KEY ...]``: play a bag into the live services on the bag's time (the command's arguments:
services/cli/replay.py).

PATH is a zagv recording, any ROS 2 bag (MCAP or sqlite3) or a ROS 1 ``.bag``. Messages are published on
``agv/<id>/<name>`` at their log time scaled by ``--rate``, and ``clock`` is published (every ``--clock-period`` s of
bag time and before each message) so that services started with ``--use-sim-time`` run on the bag's time; a
``clock`` topic in the bag itself is not replayed. ``--start``/``--end`` are seconds from the bag's start;
``--remap FROM:=TO`` renames a topic; ``--loop`` starts over (the clock jumps back, which services treat as a
restart). Every message is put with blocking congestion control: a consumer that falls behind slows the replay down
instead of losing messages. On a terminal, space pauses and resumes and ``s`` steps one message while paused. Topics
whose type has no zagv counterpart, or whose messages are malformed, are reported per topic and skipped.

Recorded service requests (rosbag2's ``--publish-service-requests``): when the bag holds ``<query>/_service_event``
topics (``localization/nomotion``: the updates at rest nav asked for), their requests are issued again, each just
before the message it was served on live (``services/recorder/service_requests.py``), and the replay waits (at most
``--service-timeout`` s) until the service has taken it; the recorded events themselves are not published. At the
end a line says how many were issued and how many were served on the same message as live. ``--no-service-requests``
plays the bag's topics only.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from dataclasses import dataclass

import zenoh

from proto import codec
from proto.keys import Keys
from proto.messages import Clock
from proto.registry import TOPICS
from services.common.service_events import query_of
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.recorder.requester import ServiceRequester
from services.recorder.service_requests import RequestSchedule, recorded_requests
from services.recorder.source import BagSource


@dataclass
class ReplayOptions:
    """How ``zagv replay`` plays a bag (its options, services/cli/replay.py)."""

    rate: float = 1.0  # bag s per wall s (0: as fast as possible)
    start_s: float = 0.0  # from the bag's start
    end_s: float | None = None  # from the bag's start (None: the bag's end)
    loop: bool = False
    paused: bool = False
    publish_clock: bool = True
    clock_period_s: float = 0.01  # bag s
    quiet: bool = False
    service_requests: bool = True
    service_timeout_s: float = 10.0  # wall s


class Control:
    """Pause/step state, driven from the keyboard on a terminal."""

    def __init__(self, paused: bool) -> None:
        self.paused = paused
        self.steps = 0
        self.changed = threading.Event()

    def toggle(self) -> None:
        self.paused = not self.paused
        self.changed.set()

    def step(self) -> None:
        self.steps += 1
        self.changed.set()

    def wait_turn(self) -> float:
        """Block while paused (returns the wall seconds spent paused); a step lets one message through."""
        t0 = time.monotonic()
        while self.paused and self.steps == 0:
            self.changed.wait(0.1)
            self.changed.clear()
        if self.paused and self.steps:
            self.steps -= 1
        return time.monotonic() - t0


def _keyboard(control: Control) -> None:
    import termios
    import tty

    fd = sys.stdin.fileno()
    old = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        while True:
            ch = sys.stdin.read(1)
            if ch == " ":
                control.toggle()
            elif ch in "sS":
                control.step()
            elif not ch:
                return
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, old)


def progress_bar(done_s: float, total_s: float, rate: float, count: int, paused: bool, width: int = 30) -> str:
    frac = 0.0 if total_s <= 0 else min(1.0, max(0.0, done_s / total_s))
    bar = "#" * int(frac * width) + "." * (width - int(frac * width))
    state = " PAUSED" if paused else ""
    return f"[{bar}] {frac * 100:5.1f}%  {done_s:7.1f}/{total_s:.1f} s  x{rate:g}  {count} msgs{state}"


def replay(settings: ZenohSettings, keys: Keys, path: str, wanted: set[str] | None, remaps: dict[str, str],
           options: ReplayOptions) -> int:
    """Play the bag at ``path`` (topics ``wanted``, None: all, renamed by ``remaps``) into the robot's keys; the
    exit code of ``zagv replay`` (2: no such bag)."""
    control = Control(options.paused)
    if sys.stdin.isatty():
        threading.Thread(target=_keyboard, args=(control,), daemon=True).start()
    session = open_session(settings)
    publishers: dict[str, object] = {}

    def publisher(name: str):  # zenoh.Publisher
        # a bag is played to be processed whole: block under congestion instead of Zenoh's default of dropping
        # after a millisecond (a loaded consumer lost two thirds of a log's scans that way)
        if name not in publishers:
            publishers[name] = session.declare_publisher(keys(name), congestion_control=zenoh.CongestionControl.BLOCK)
        return publishers[name]

    total = 0
    requester = None
    try:
        with BagSource(path) as source:
            start_ns = source.start_ns + int(options.start_s * 1e9)
            end_ns = source.start_ns + int(options.end_s * 1e9) if options.end_s is not None else source.end_ns
            total_s = (end_ns - start_ns) / 1e9
            requests = recorded_requests(source, start_ns, end_ns) if options.service_requests else []
            if requests:
                requester = ServiceRequester(session, keys, {r.query for r in requests}, options.service_timeout_s)
            while True:
                count = _play_once(options, source, start_ns, end_ns, total_s, wanted, remaps, control, publisher,
                                   requests, requester)
                total += count
                if not options.loop:
                    break
            if requester is not None:
                print(f"zagv replay: {requester.summary()}", file=sys.stderr)
            for topic, reason in sorted(source.problems.items()):
                print(f"zagv replay: skipped {source.skipped[topic]} message(s) on {topic}: {reason}",
                      file=sys.stderr)
    except KeyboardInterrupt:
        pass
    except FileNotFoundError as exc:
        print(f"zagv replay: {exc}", file=sys.stderr)
        return 2
    finally:
        if requester is not None:
            requester.close()
        for pub in publishers.values():
            with contextlib.suppress(Exception):
                pub.undeclare()  # type: ignore[attr-defined]
        session.close()
    print(f"zagv replay: {total} messages published")
    return 0


def _play_once(options, source, start_ns, end_ns, total_s, wanted, remaps, control, publisher, requests=(),
               requester = None) -> int:
    """One pass over [start_ns, end_ns]; returns the messages published."""
    clock_pub = publisher("clock") if options.publish_clock else None
    rate = options.rate
    wall0 = time.monotonic()
    period_ns = int(options.clock_period_s * 1e9)
    next_tick = start_ns
    count = 0
    next_print = 0.0

    def wait_until(t_ns: int) -> None:
        nonlocal wall0
        if rate > 0:
            target = wall0 + (t_ns - start_ns) / 1e9 / rate
            delay = target - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def tick(t_ns: int) -> None:
        if clock_pub is not None:
            clock_pub.put(codec.encode(Clock(stamp=t_ns / 1e9, speed_factor=rate if rate > 0 else 0.0)))

    played = None if wanted is None else {remaps.get(n, n) for n in wanted}
    if requester is not None:
        schedule = RequestSchedule(list(requests), played)
    else:
        schedule = None
    for t_ns, name, msg in source.messages(start_ns, end_ns, wanted):
        if name == "clock" or (wanted is not None and name not in wanted):
            continue
        if schedule is not None and query_of(name) is not None:
            continue  # the live service publishes its own events for the requests issued again
        target = remaps.get(name, name)
        if target not in TOPICS or type(msg) is not TOPICS[target]:
            source.problems.setdefault("/" + name, f"no zagv topic {target!r} of type {type(msg).__name__}")
            source.skipped["/" + name] += 1
            continue
        paused_s = control.wait_turn()
        wall0 += paused_s
        if control.paused:  # stepping: the clock follows the stepped message
            wall0 = time.monotonic() - (t_ns - start_ns) / 1e9 / (rate or 1.0)
        while clock_pub is not None and period_ns > 0 and next_tick < t_ns:
            wait_until(next_tick)
            tick(next_tick)
            next_tick += period_ns
        wait_until(t_ns)
        tick(t_ns)
        if schedule is not None and requester is not None:
            for req in schedule.due(t_ns, target, getattr(msg, "stamp", None)):
                requester.issue(req)
        publisher(target).put(codec.encode(msg))
        count += 1
        if not options.quiet and time.monotonic() >= next_print:
            next_print = time.monotonic() + 0.5
            print("\r" + progress_bar((t_ns - start_ns) / 1e9, total_s, rate, count, control.paused), end="",
                  file=sys.stderr, flush=True)
    if not options.quiet:
        print("\r" + progress_bar(total_s, total_s, rate, count, False), file=sys.stderr, flush=True)
    return count
