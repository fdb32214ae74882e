"""The fixed-rate control loop on its own thread: commands out every cycle, feedback into odometry, faults.

Each cycle: latest ``cmd_vel`` (zero after ``cmd_timeout_s``, reached through the acceleration limits,
i.e. a controlled deceleration) -> limits -> IK -> optimisation -> RPDO to every controller (this also feeds their
command watchdogs); TPDO feedback -> FK -> odometry. A lost link (heartbeat, bus error, silent feedback), a fault
flag, disable or e-stop make the cycle command zero speed; a reconnect thread reopens the link with exponential
backoff while the loop keeps publishing (``link_ok`` false, the fault text set). Odometry continues from its pose.

The controllers hold their own e-stop (``!EX``, fault flag bit 4), which outlives this process: a controller that
reports it while the drive is not e-stopped (a drive restarted after an e-stop, or the controller's own e-stop
input) puts the drive in the e-stopped state, so that only an explicit ``drive/release`` (``!MG``) ends it. For
``RELEASE_GRACE_S`` after a release the flag is still expected in feedback sent before ``!MG`` arrived.

Timing: ``WallTicker`` sleeps to just before each deadline and spins the rest (the period is measured with
``perf_counter``); ``SimTicker`` follows the simulator's clock messages (sim seconds). A new ``cmd_vel`` can wake
the loop for an immediate extra cycle (``wake_on_command``), so a command reaches the bus without waiting for the
next tick; such cycles are left out of the period statistics.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from services.drive.canlink import FF_ESTOP, LinkError, RoboteqLink
from services.drive.controller import CommandResult, DriveController, ModuleFeedback, WheelOdometry
from services.drive.kinematics import ZERO_TWIST, Twist

log = logging.getLogger("zagv.drive.loop")

#: after a release, feedback may show the controllers' e-stop flag for this long (ticker s) before it is believed
RELEASE_GRACE_S = 1.0
#: a clock step back by more than this (ticker s) is a restart of the clock's source, not reordering
CLOCK_RESTART_S = 1.0


# --------------------------------------------------------------------------- timing


class LoopStats:
    """Periods of the last ``window`` scheduled cycles: achieved rate, jitter |period - nominal| p99, overruns."""

    def __init__(self, nominal_period_s: float, window: int = 2000) -> None:
        self.nominal_period_s = nominal_period_s
        self.periods: collections.deque[float] = collections.deque(maxlen=window)
        self.overruns = 0
        self.cycles = 0
        self.extra_cycles = 0
        self._jitter_ms = 0.0
        self._jitter_at: float | None = None

    def record(self, period_s: float) -> None:
        self.periods.append(period_s)

    @property
    def hz(self) -> float:
        if not self.periods:
            return 0.0
        mean = sum(self.periods) / len(self.periods)
        return 1.0 / mean if mean > 0 else 0.0

    def jitter_p99_ms(self, max_age_s: float = 1.0) -> float:
        """p99 of |period - nominal| over the window (ms), recomputed at most every ``max_age_s`` (wall time): a
        percentile of 2000 periods costs ~50 us, too much for every published snapshot."""
        if not self.periods:
            return 0.0
        now = time.monotonic()
        if self._jitter_at is None or now - self._jitter_at >= max_age_s:
            dev = np.abs(np.fromiter(self.periods, float) - self.nominal_period_s)
            self._jitter_ms = float(np.percentile(dev, 99)) * 1e3
            self._jitter_at = now
        return self._jitter_ms


class WallTicker:
    """Deadlines on ``perf_counter``: sleep until ``spin_s`` before each, then busy-wait (sub-0.1 ms wake-ups)."""

    is_sim = False

    def __init__(self, hz: float, spin_s: float = 0.0003) -> None:
        self.period_s = 1.0 / hz
        self.spin_s = max(0.0, spin_s)
        #: ``perf_counter`` + this = Unix time (the service clock): messages are stamped on the clock every other
        #: service reads, the loop times itself on ``perf_counter``
        self.stamp_offset_s = time.time() - time.perf_counter()
        self._next: float | None = None
        self._poke = threading.Event()
        self.overruns = 0

    def now(self) -> float:
        return time.perf_counter()

    def poke(self) -> None:
        """Wake the waiting loop for an immediate extra cycle."""
        self._poke.set()

    def wait(self, stop: threading.Event) -> tuple[float, bool]:
        """Block until the next deadline (-> (now, True)) or a poke (-> (now, False)); returns early on ``stop``."""
        now = time.perf_counter()
        if self._next is None:
            self._next = now
        deadline = self._next
        while not stop.is_set():
            now = time.perf_counter()
            remaining = deadline - now
            if remaining <= 0.0:
                break
            if self._poke.is_set():
                self._poke.clear()
                return now, False
            if remaining > self.spin_s:
                self._poke.wait(remaining - self.spin_s)
        if now > deadline + 0.5 * self.period_s:
            self.overruns += 1
            self._next = now + self.period_s
        else:
            self._next = deadline + self.period_s
        self._poke.clear()
        return now, True


class SimTicker:
    """Deadlines on the simulator's clock: ``advance(t)`` (any thread) moves sim time; waiters wake when due."""

    is_sim = True

    def __init__(self, hz: float) -> None:
        self.period_s = 1.0 / hz
        self.stamp_offset_s = 0.0  #: ticker time is the sim clock's time
        self._now = 0.0
        self._started = False
        self._next: float | None = None
        self._cond = threading.Condition()
        self._poked = False
        self.overruns = 0  # clock steps longer than 1.5 periods (the clock's granularity, not the loop's fault)

    def now(self) -> float:
        return self._now

    def advance(self, t: float) -> None:
        """Take sim time ``t``; the loop's thread is woken only when its next cycle is due (the clock ticks at
        twice the loop's rate), on the first tick and when the simulator restarted."""
        with self._cond:
            restarted = t < self._now - 1.0
            if restarted:
                self._next = None
            elif t < self._now:
                return
            self._now = t
            first, self._started = not self._started, True
            if first or restarted or self._next is None or t >= self._next:
                self._cond.notify_all()

    def poke(self) -> None:
        with self._cond:
            self._poked = True
            self._cond.notify_all()

    def wait(self, stop: threading.Event) -> tuple[float, bool]:
        with self._cond:
            while not stop.is_set():
                if self._started:
                    if self._next is None:
                        self._next = self._now
                    if self._now >= self._next:
                        break
                    if self._poked:
                        self._poked = False
                        return self._now, False
                self._cond.wait(0.1)
            now = self._now
            if self._next is None:
                return now, True
            if now > self._next + 0.5 * self.period_s:
                self.overruns += 1
                self._next = now + self.period_s
            else:
                self._next += self.period_s
            self._poked = False
            return now, True


# --------------------------------------------------------------------------- publishing


def publish_due(now: float, next_publish: float, published_stamp: float) -> bool:
    """Whether a cycle at ``now`` publishes: its time is due and later than the last published stamp.

    One message per stamp: when the clock did not advance between cycles (a sim clock step longer than the loop
    period, or an extra cycle woken by a command), the odometry integrated since is published with the next, later
    stamp, never under the stamp already sent with another pose.
    """
    return now >= next_publish and now > published_stamp


def next_publish_time(now: float, next_publish: float, period_s: float) -> float:
    """The next publish deadline after publishing at ``now``: on the ``period_s`` grid, re-anchored at ``now`` when
    the clock jumped past it (a late cycle publishes at the next one rather than in a burst)."""
    return max(next_publish + period_s, now) if math.isfinite(next_publish) else now + period_s


# --------------------------------------------------------------------------- the loop


@dataclass(frozen=True)
class LoopSettings:
    cmd_timeout_s: float = 0.2
    publish_period_s: float = 0.02
    reconnect_initial_s: float = 0.2
    reconnect_max_s: float = 2.0
    fault_mask: int = 0x7F
    imu_yaw_fusion: bool = False
    imu_yaw_weight: float = 1.0
    imu_timeout_s: float = 0.2
    wake_on_command: bool = True
    realtime_priority: int = 0
    rpdo_refresh_s: float = 0.1


@dataclass(frozen=True)
class Snapshot:
    """What the loop publishes: everything the node needs for ``odom`` and ``wheels``."""

    stamp: float  #: s on the service clock (Unix or sim time) of the cycle that read the feedback; unique per snapshot
    result: CommandResult
    feedback: tuple[ModuleFeedback, ...]
    measured_angles: tuple[float, ...]
    measured_speeds: tuple[float, ...]
    pose: tuple[float, float, float]
    twist: Twist
    residual_mps: float
    enabled: bool
    estopped: bool
    link_ok: bool
    fault: str
    loop_hz: float
    jitter_p99_ms: float
    overruns: int


class DriveLoop:
    """Owns the controller, odometry and the CAN link; ``start()`` runs it on a thread, ``cycle()`` is one step."""

    def __init__(self, controller: DriveController, odometry: WheelOdometry, link_factory: Callable[[], RoboteqLink],
                 ticker: WallTicker | SimTicker, settings: LoopSettings,
                 publish: Callable[[Snapshot], None] | None = None, *, enabled: bool = True) -> None:
        self.controller = controller
        self.odometry = odometry
        self.link_factory = link_factory
        self.ticker = ticker
        self.settings = settings
        self.publish = publish
        self.stats = LoopStats(ticker.period_s)
        self.enabled = enabled
        self.estopped = False
        self._released_at = -math.inf
        self.link: RoboteqLink | None = None
        self.link_ok = False
        self.link_fault = "CAN link not yet open"
        self.flag_fault = ""
        self.cmd_rejected = 0
        self.reconnects = 0
        self.link_attempts = 0  #: CAN link openings tried (readiness: the link is up or reported down)
        self.cycle_errors = 0
        self._cmd: Twist | None = None
        self._cmd_at = -math.inf
        self._cmd_lock = threading.Lock()
        self._cmd_rx_perf = 0.0
        self._cmd_rx_done = 0.0
        #: wall seconds from a cmd_vel's arrival to the write of the RPDO frames that carry it (last 1000)
        self.cmd_latency: collections.deque[float] = collections.deque(maxlen=1000)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reconnector: threading.Thread | None = None
        self._needs_reset = True
        self._last_now: float | None = None
        self._last_periodic: float | None = None
        self._next_publish = -math.inf
        self._published_stamp = -math.inf  #: ticker time of the last published snapshot (stamps strictly increase)
        self._imu_rate: tuple[float, float] | None = None  # (yaw rate rad/s, monotonic time)
        self.last_snapshot: Snapshot | None = None
        self._last_sent: tuple | None = None
        self._last_sent_at = -math.inf

    # ------------------------------------------------------------------ inputs (any thread)

    def set_command(self, vx: float, vy: float, wz: float) -> bool:
        """Take a new body twist command; a non-finite one is refused (returns False) and never reaches a motor."""
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(wz)):
            self.cmd_rejected += 1
            return False
        with self._cmd_lock:
            self._cmd = Twist(vx, vy, wz)
            self._cmd_at = self.ticker.now()
            self._cmd_rx_perf = time.perf_counter()
        if self.settings.wake_on_command:
            self.ticker.poke()
        return True

    def cmd_latency_ms(self, percentile: float) -> float:
        """A percentile of ``cmd_latency`` in ms (0 before any command)."""
        if not self.cmd_latency:
            return 0.0
        return float(np.percentile(np.fromiter(self.cmd_latency, float), percentile)) * 1e3

    def set_imu_yaw_rate(self, wz_radps: float) -> None:
        if math.isfinite(wz_radps):
            self._imu_rate = (wz_radps, time.monotonic())

    def released(self) -> None:
        """The controllers acknowledged ``!MG``: leave the e-stopped state (enable stays as it was)."""
        self.controller.reset()
        self._released_at = self.ticker.now()
        self.estopped = False

    def _adopt_controller_estop(self, now: float, feedback: list[ModuleFeedback]) -> None:
        """A controller that holds an e-stop puts the drive in the e-stopped state (see the module docstring)."""
        if self.estopped or now - self._released_at < RELEASE_GRACE_S:
            return
        held = [node_id for node_id, f in zip(self._node_ids(), feedback) if f.fault_flags & FF_ESTOP]
        if held:
            self.estopped = True
            log.warning("controller node(s) %s hold an e-stop: drive e-stopped until drive/release",
                        ", ".join(map(str, held)))

    # ------------------------------------------------------------------ lifetime

    def start(self) -> None:
        self._stop.clear()
        self._start_reconnect("CAN link not yet open", initial=True)
        self._thread = threading.Thread(target=self._run, name="drive-loop", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 3.0) -> None:
        self._stop.set()
        self.ticker.poke()
        for t in (self._thread, self._reconnector):
            if t is not None:
                t.join(timeout_s)
        link, self.link = self.link, None
        self.link_ok = False
        if link is not None:
            with contextlib.suppress(LinkError):  # leave the motors stopped, not at the last speed
                link.send(self.controller.stop().motors)
            link.close()

    def _run(self) -> None:
        prio = self.settings.realtime_priority
        if prio > 0:
            try:  # Linux: applies to the calling thread only
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
                log.info("control thread runs SCHED_FIFO priority %d", prio)
            except (OSError, AttributeError) as exc:
                log.warning("cannot give the control thread real-time priority %d: %s", prio, exc)
        while not self._stop.is_set():
            now, periodic = self.ticker.wait(self._stop)
            if self._stop.is_set():
                break
            try:
                self.cycle(now, periodic)
            except Exception:  # no frame this cycle: the controllers' watchdog stops the motors if it persists
                self.cycle_errors += 1
                if self.cycle_errors in (1, 10, 100) or self.cycle_errors % 1000 == 0:
                    log.exception("control cycle failed (%d so far)", self.cycle_errors)

    # ------------------------------------------------------------------ one cycle

    def cycle(self, now: float, periodic: bool = True) -> Snapshot | None:
        """Run one control cycle at time ``now`` (ticker clock). Returns the snapshot when it was published."""
        s = self.settings
        if self._last_now is not None and now < self._last_now - CLOCK_RESTART_S:
            self._restart_epoch(now)
        if periodic:
            if self._last_periodic is not None:
                self.stats.record(now - self._last_periodic)
            self._last_periodic = now
            self.stats.cycles += 1
        else:
            self.stats.extra_cycles += 1
        dt = 0.0 if self._last_now is None else min(max(now - self._last_now, 0.0), 0.1)
        self._last_now = now

        link = self.link if self.link_ok else None
        if link is not None:
            try:
                link.poll()
                reason = link.health()
            except LinkError as exc:
                reason = str(exc)
            if reason:
                self._link_lost(reason)
                link = None
        feedback: list[ModuleFeedback] = link.feedback() if link is not None else []
        angles = [u.counts_to_rad(f.steer_counts) for u, f in zip(self.controller.units, feedback)]
        if link is not None and self._needs_reset:
            # motion restarts from rest; odometry keeps its count baseline, so what the wheels did while the link
            # was down is still integrated (a restarted counter shows as an implausible step and is re-baselined)
            self.controller.reset(angles)
            self._needs_reset = False
        self._adopt_controller_estop(now, feedback)
        self.flag_fault = self._check_flags(feedback, now)

        with self._cmd_lock:
            cmd, cmd_at, cmd_rx = self._cmd, self._cmd_at, self._cmd_rx_perf
        if link is None or not self.enabled or self.estopped or self.flag_fault:
            result = self.controller.stop()
        else:
            fresh = cmd is not None and now - cmd_at <= s.cmd_timeout_s
            result = self.controller.command(cmd if cmd is not None and fresh else ZERO_TWIST, dt, angles or None)
        if link is not None and (result.motors != self._last_sent or now - self._last_sent_at >= s.rpdo_refresh_s):
            try:
                link.send(result.motors)
                self._last_sent, self._last_sent_at = result.motors, now
            except LinkError as exc:
                self._link_lost(str(exc))
                link = None
        if cmd_rx != self._cmd_rx_done:  # a new command went out this cycle: time its way through the drive
            self._cmd_rx_done = cmd_rx
            if link is not None:
                self.cmd_latency.append(time.perf_counter() - cmd_rx)

        if link is not None and feedback:
            dyaw = None
            if s.imu_yaw_fusion and self._imu_rate is not None and \
                    time.monotonic() - self._imu_rate[1] <= s.imu_timeout_s:
                dyaw = self._imu_rate[0] * dt
            self.odometry.update(feedback, dyaw, s.imu_yaw_weight)

        if publish_due(now, self._next_publish, self._published_stamp):
            self._next_publish = next_publish_time(now, self._next_publish, s.publish_period_s)
            self._published_stamp = now
            snap = self._snapshot(now, result, feedback, angles)
            self.last_snapshot = snap
            if self.publish is not None:
                self.publish(snap)
            return snap
        return None

    def _restart_epoch(self, now: float) -> None:
        """The clock jumped back (the simulator restarted): drop every time held from the old run.

        Held times would compare as far in the future: no snapshot until the new clock caught up with the next
        publish time, and a command from the old run would count as fresh. The command is dropped, so nothing moves
        until a new one arrives."""
        log.warning("clock jumped back from %.3f to %.3f s: the loop starts a new epoch", self._last_now or 0.0, now)
        with self._cmd_lock:
            self._cmd, self._cmd_at = None, -math.inf
        self._released_at = -math.inf
        self._last_now = self._last_periodic = None
        self._next_publish = self._last_sent_at = self._published_stamp = -math.inf

    def _check_flags(self, feedback: list[ModuleFeedback], now: float) -> str:
        faults = []
        for node_id, f in zip(self._node_ids(), feedback):
            ff = f.fault_flags & self.settings.fault_mask
            if self.estopped or now - self._released_at < RELEASE_GRACE_S:
                ff &= ~FF_ESTOP
            if ff:
                faults.append(f"node {node_id} fault flags 0x{ff:02X}" + (" (emergency stop)" if ff & FF_ESTOP
                                                                          else ""))
        return "; ".join(faults)

    def _node_ids(self) -> tuple[int, ...]:
        link = self.link
        return link.settings.node_ids if link is not None else ()

    def _snapshot(self, now: float, result: CommandResult, feedback: list[ModuleFeedback],
                  angles: list[float]) -> Snapshot:
        odo = self.odometry
        speeds = tuple(u.rpm_to_mps(f.traction_rpm) for u, f in zip(self.controller.units, feedback))
        fault = self.link_fault if not self.link_ok else self.flag_fault
        return Snapshot(
            stamp=now + self.ticker.stamp_offset_s, result=result, feedback=tuple(feedback),
            measured_angles=tuple(angles), measured_speeds=speeds, pose=(odo.pose.x, odo.pose.y, odo.pose.theta),
            twist=odo.twist if self.link_ok else ZERO_TWIST, residual_mps=odo.residual_mps, enabled=self.enabled,
            estopped=self.estopped, link_ok=self.link_ok, fault=fault, loop_hz=self.stats.hz,
            jitter_p99_ms=self.stats.jitter_p99_ms(), overruns=self.ticker.overruns)

    # ------------------------------------------------------------------ link recovery

    def _link_lost(self, reason: str) -> None:
        if not self.link_ok:
            return
        self._last_sent = None
        log.warning("CAN link lost: %s; stopping and reconnecting", reason)
        self.link_ok = False
        self.controller.stop()
        self._start_reconnect(reason)

    def _start_reconnect(self, reason: str, initial: bool = False) -> None:
        self.link_fault = reason
        old, self.link = self.link, None
        self._reconnector = threading.Thread(target=self._reconnect, args=(old, initial), name="drive-reconnect",
                                             daemon=True)
        self._reconnector.start()

    def _reconnect(self, old: RoboteqLink | None, initial: bool) -> None:
        if old is not None:
            old.close()
        delay = self.settings.reconnect_initial_s
        attempt = 0
        while not self._stop.is_set():
            if not initial or attempt > 0:
                self._stop.wait(delay)  # wall time: the bus and its server live in wall time
                if self._stop.is_set():
                    return
                delay = min(delay * 2.0, self.settings.reconnect_max_s)
            attempt += 1
            link = self.link_factory()
            try:
                link.open()
            except LinkError as exc:
                if attempt == 1 or attempt % 10 == 0:
                    log.warning("CAN link attempt %d failed: %s", attempt, exc)
                self.link_fault = str(exc)
                self.link_attempts += 1
                continue
            if self.estopped:
                failures = link.estop()
                if failures:
                    log.warning("re-sending e-stop after reconnect: %s", "; ".join(failures))
            self._needs_reset = True
            self.link = link
            self.link_fault = ""
            self.link_ok = True
            self.link_attempts += 1
            if not initial:
                self.reconnects += 1
            log.info("CAN link %s after %d attempt(s)", "up" if initial else "restored", attempt)
            return
