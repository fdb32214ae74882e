"""The recorder service: the black box.

Keeps every topic's raw payloads (``proto.registry.TOPICS`` but ``exclude``) of the last ``window_s`` (clock time)
in memory and writes them as a rosbag2/MCAP bag (``blackbox_<time>_<reason>/`` in the black box folder) when the
drive e-stops or reports a fault (``wheels``), when a goal fails (``nav/status``), when another service's health
token disappears (a crash), and on demand through the ``recorder/save`` query (HMI, ``zagv blackbox save``). Each
topic arrives through the key's shared reader ring (``Node.subscribe_raw``): a process too busy to keep up loses its
oldest samples rather than stall a publisher. A save waits ``post_trigger_s`` of clock
time so that the bag shows the aftermath too, then writes on a worker thread.
"""

from __future__ import annotations

import asyncio
import functools
import shutil
import time
from pathlib import Path
from typing import Any

import zenoh

from proto.messages import BlackBoxSaveRequest, NavStatus, Reply, WheelStates
from proto.registry import TOPICS
from services.common.service import ServiceContext
from services.recorder.blackbox import RingBuffer, Triggers, bag_name, save
from services.recorder.config import RecorderConfig


class BlackBox:
    """The black box: a ring buffer of every topic, saved as a bag on a trigger or on request."""

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.cfg: RecorderConfig = ctx.config["recorder"]
        self.node = ctx.node
        self.clock = ctx.node.clock
        self.folder = Path(self.cfg.directory()).expanduser()
        self.ring = RingBuffer(self.cfg.window_s)
        self.triggers = Triggers()
        self.last_save_s = -float("inf")
        self.saving: set[str] = set()
        self.excluded = set(self.cfg.exclude)

    def record(self, name: str, sample: zenoh.Sample) -> None:
        """Keep ``sample`` of topic ``name`` (reader thread), stamped with the clock's time of arrival."""
        self.ring.add(name, sample.payload.to_bytes(), int(round(self.clock.now() * 1e9)))

    def may_save(self, reason: str, now: float, on_demand: bool) -> bool:
        """A trigger saves at most once per ``cooldown_s`` and not while the same reason is being saved;
        a request always saves."""
        if not self.cfg.blackbox:
            return False
        return on_demand or not (now - self.last_save_s < self.cfg.cooldown_s or reason in self.saving)

    async def save_now(self, reason: str, *, on_demand: bool = False) -> Path | None:
        cfg, clock = self.cfg, self.clock
        now = clock.now()
        if not self.may_save(reason, now, on_demand):
            return None
        self.last_save_s = now
        self.saving.add(reason)
        try:
            if not on_demand and cfg.post_trigger_s > 0:
                await clock.sleep(cfg.post_trigger_s)
                if self.ctx.stop.is_set():  # the stack is stopping: health tokens going away are not crashes
                    return None
            items = self.ring.snapshot()
            self.folder.mkdir(parents=True, exist_ok=True)
            out = self.folder / bag_name(time.strftime("%Y%m%d_%H%M%S"), reason)
            n = 2
            while out.exists():
                out = out.with_name(f"{out.name.rsplit('~', 1)[0]}~{n}")
                n += 1
            path, count = await asyncio.to_thread(save, items, out, self.node.keys.robot_id)
            span = (items[-1][0] - items[0][0]) / 1e9 if items else 0.0
            self.node.log.info("black box saved: %s (%s, %d messages, %.1f s)", path, reason, count, span)
            _prune(self.folder, cfg.max_saved)
            return path
        finally:
            self.saving.discard(reason)

    def trigger(self, reason: str | None) -> None:
        if reason:
            self.node.log.warning("black box trigger: %s", reason)
            self.node.spawn(self.save_now(reason))

    def trigger_threadsafe(self, reason: str | None) -> None:
        """``trigger`` from a reader thread."""
        if reason:
            self.node.loop.call_soon_threadsafe(self.trigger, reason)

    def on_health(self, sample: zenoh.Sample) -> None:
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.DELETE and service != self.node.name and not self.ctx.stop.is_set():
            self.node.loop.call_soon_threadsafe(self.trigger, f"crash-{service}")

    async def on_save(self, req: BlackBoxSaveRequest) -> Reply:
        if not self.cfg.blackbox:
            return Reply(ok=False, message="the black box is off ([recorder] blackbox = false)")
        path = await self.save_now(req.reason or "on-demand", on_demand=True)
        return Reply(ok=path is not None, message=str(path) if path else "nothing saved")

    def wire(self) -> list[Any]:
        """Subscribe to every recorded topic (and to the health tokens for crashes) and answer recorder/save; the
        Zenoh subscribers to undeclare at the end (the node undeclares its own)."""
        node, cfg = self.node, self.cfg
        subs: list[Any] = []
        if cfg.blackbox:
            # each recorded topic through the process's shared reader of its key: in a container, where the other
            # services read most of these keys already, a message costs the black box no thread wake-up of its own
            # (a subscriber on agv/<id>/** did: one per message of every topic)
            recorded = sorted(set(TOPICS) - self.excluded)
            for name in recorded:
                node.subscribe_raw(name, functools.partial(self.record, name))
            if "map" in recorded:  # latched and published rarely: the map already out goes into the box too
                node.session.get(node.keys("map"), lambda r: self.record("map", r.ok) if r.ok is not None else None,
                                 timeout=2.0)
            # edge detection on the reader threads (each touches its own fields of Triggers); the loop is woken
            # only when a save is due, not for each of the drive's 50 wheel states a second
            node.subscribe("wheels", lambda w: self.trigger_threadsafe(self.triggers.on_wheels(w)),
                           msg_type=WheelStates, on_zenoh_thread=True)
            node.subscribe("nav/status", lambda s: self.trigger_threadsafe(self.triggers.on_nav_status(s)),
                           msg_type=NavStatus, on_zenoh_thread=True)
            if cfg.save_on_crash:
                subs.append(node.session.liveliness().declare_subscriber(node.keys.health_all, self.on_health))
        node.queryable("recorder/save", self.on_save)
        return subs

    async def report(self) -> None:
        while True:
            self.node.extra_stats.update(buffered_messages=len(self.ring), buffered_mb=round(self.ring.bytes / 1e6, 2))
            await asyncio.sleep(1.0)


async def run(ctx: ServiceContext) -> None:
    box = BlackBox(ctx)
    node = ctx.node
    subs = box.wire()
    node.extra_stats.update(blackbox_dir=str(box.folder), window_s=box.cfg.window_s)
    node.ready("subscribed to every topic; recorder/save answered" if box.cfg.blackbox else "black box off")
    node.spawn(box.report())
    try:
        await ctx.stop.wait()
    finally:
        for s in subs:
            s.undeclare()


def _prune(folder: Path, keep: int) -> None:
    bags = sorted((d for d in folder.glob("blackbox_*") if d.is_dir()), key=lambda d: d.stat().st_mtime)
    for old in bags[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
