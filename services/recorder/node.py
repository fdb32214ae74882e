"""The recorder service: the black box.

Keeps every topic's raw payloads of the last ``window_s`` (clock time) in memory and writes them as a rosbag2/MCAP
bag (``blackbox_<time>_<reason>/`` in the black box folder) when the drive e-stops or reports a fault
(``wheels``), when a goal fails (``nav/status``), when another service's health token disappears (a crash), and on
demand through the ``recorder/save`` query (HMI, ``zagv blackbox save``). A save waits ``post_trigger_s`` of clock
time so that the bag shows the aftermath too, then writes on a worker thread.
"""

from __future__ import annotations

import asyncio
import shutil
import time
from pathlib import Path

import zenoh

from proto.keys import split_key
from proto.messages import BlackBoxSaveRequest, NavStatus, Reply, WheelStates
from proto.registry import TOPICS
from services.common.service import ServiceContext
from services.recorder.blackbox import RingBuffer, Triggers, bag_name, save
from services.recorder.config import RecorderConfig


async def run(ctx: ServiceContext) -> None:
    cfg: RecorderConfig = ctx.config["recorder"]
    node = ctx.node
    clock = node.clock
    folder = Path(cfg.directory()).expanduser()
    ring = RingBuffer(cfg.window_s)
    triggers = Triggers()
    last_save_s = -float("inf")
    saving: set[str] = set()
    excluded = set(cfg.exclude)

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            _, name = split_key(str(sample.key_expr))
        except ValueError:
            return
        if name in TOPICS and name not in excluded:
            ring.add(name, sample.payload.to_bytes(), int(round(clock.now() * 1e9)))

    async def save_now(reason: str, *, on_demand: bool = False) -> Path | None:
        nonlocal last_save_s
        if not cfg.blackbox:
            return None
        now = clock.now()
        if not on_demand and (now - last_save_s < cfg.cooldown_s or reason in saving):
            return None
        last_save_s = now
        saving.add(reason)
        try:
            if not on_demand and cfg.post_trigger_s > 0:
                await clock.sleep(cfg.post_trigger_s)
                if ctx.stop.is_set():  # the stack is stopping: health tokens going away are not crashes
                    return None
            items = ring.snapshot()
            folder.mkdir(parents=True, exist_ok=True)
            out = folder / bag_name(time.strftime("%Y%m%d_%H%M%S"), reason)
            n = 2
            while out.exists():
                out = out.with_name(f"{out.name.rsplit('~', 1)[0]}~{n}")
                n += 1
            path, count = await asyncio.to_thread(save, items, out, node.keys.robot_id)
            span = (items[-1][0] - items[0][0]) / 1e9 if items else 0.0
            node.log.info("black box saved: %s (%s, %d messages, %.1f s)", path, reason, count, span)
            _prune(folder, cfg.max_saved)
            return path
        finally:
            saving.discard(reason)

    def trigger(reason: str | None) -> None:
        if reason:
            node.log.warning("black box trigger: %s", reason)
            node.spawn(save_now(reason))

    def on_health(sample: zenoh.Sample) -> None:
        service = str(sample.key_expr).rsplit("/", 1)[-1]
        if sample.kind == zenoh.SampleKind.DELETE and service != node.name and not ctx.stop.is_set():
            node.loop.call_soon_threadsafe(trigger, f"crash-{service}")

    async def on_save(req: BlackBoxSaveRequest) -> Reply:
        if not cfg.blackbox:
            return Reply(ok=False, message="the black box is off ([recorder] blackbox = false)")
        path = await save_now(req.reason or "on-demand", on_demand=True)
        return Reply(ok=path is not None, message=str(path) if path else "nothing saved")

    subs = []
    if cfg.blackbox:
        subs.append(node.session.declare_subscriber(node.keys.everything, on_sample))
        node.session.get(node.keys("map"), lambda r: on_sample(r.ok) if r.ok is not None else None, timeout=2.0)
        node.subscribe("wheels", lambda w: trigger(triggers.on_wheels(w)), msg_type=WheelStates)
        node.subscribe("nav/status", lambda s: trigger(triggers.on_nav_status(s)), msg_type=NavStatus)
        if cfg.save_on_crash:
            subs.append(node.session.liveliness().declare_subscriber(node.keys.health_all, on_health))
    node.queryable("recorder/save", on_save)
    node.extra_stats.update(blackbox_dir=str(folder), window_s=cfg.window_s)
    node.ready("subscribed to every topic; recorder/save answered" if cfg.blackbox else "black box off")

    async def report() -> None:
        while True:
            node.extra_stats.update(buffered_messages=len(ring), buffered_mb=round(ring.bytes / 1e6, 2))
            await asyncio.sleep(1.0)

    node.spawn(report())
    try:
        await ctx.stop.wait()
    finally:
        for s in subs:
            s.undeclare()


def _prune(folder: Path, keep: int) -> None:
    bags = sorted((d for d in folder.glob("blackbox_*") if d.is_dir()), key=lambda d: d.stat().st_mtime)
    for old in bags[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
