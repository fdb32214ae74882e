"""``zagv topic list|echo|hz``: inspect the robot's topics like ``ros2 topic``."""

from __future__ import annotations

import argparse
import json
import queue
import sys
import threading
import time

import zenoh

from proto import codec
from proto.keys import split_key
from proto.registry import TOPICS
from services.client.connect import client_keys, client_session


def full_key(args: argparse.Namespace) -> str:
    key = args.key
    return key if key.startswith("agv/") else client_keys(args)(key)


def _drain(q: queue.Queue, timeout_s: float | None):
    try:
        return q.get(timeout=timeout_s)
    except queue.Empty:
        return None


def run_list(args: argparse.Namespace) -> int:
    keys = client_keys(args)
    seen: dict[str, int] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            k = str(sample.key_expr)
            seen[k] = seen.get(k, 0) + 1

    session = client_session(args)
    try:
        sub = session.declare_subscriber(keys.everything, on_sample)
        time.sleep(args.window)  # a listening window, not a wait for a condition
        sub.undeclare()
    finally:
        session.close()
    names = set(seen)
    if args.all:
        names |= {keys(t) for t in TOPICS}
    for k in sorted(names):
        try:
            type_name = codec.topic_type(k).__name__
        except KeyError:
            type_name = "?"
        rate = seen.get(k, 0) / args.window
        print(f"{k:<40} {type_name:<20} {rate:8.1f} Hz")
    return 0


def format_message(key: str, payload: bytes, as_json: bool) -> str:
    try:
        msg = codec.decode_any(key, payload)
    except (KeyError, codec.ProtoDecodeError) as exc:
        return json.dumps({"key": key, "error": str(exc)}) if as_json else f"{key}: <{exc}>"
    if as_json:
        return codec.to_json(msg)
    try:
        _, name = split_key(key)
    except ValueError:
        name = key
    return f"--- {name} ({type(msg).__name__})\n{json.dumps(codec.to_display(msg), indent=2)}"


def run_echo(args: argparse.Namespace) -> int:
    q: queue.Queue[tuple[str, bytes]] = queue.Queue()
    session = client_session(args)
    try:
        session.declare_subscriber(full_key(args), lambda s: q.put((str(s.key_expr), s.payload.to_bytes())))
        n = 0
        while args.count == 0 or n < args.count:
            item = _drain(q, args.timeout or None)
            if item is None:
                print(f"zagv topic echo: no message on {full_key(args)} within {args.timeout} s", file=sys.stderr)
                return 1
            key, payload = item
            print(format_message(key, payload, as_json=args.json), flush=True)
            n += 1
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    return 0


def run_hz(args: argparse.Namespace) -> int:
    stamps: list[float] = []
    lock = threading.Lock()

    def on_sample(_sample: zenoh.Sample) -> None:
        with lock:
            stamps.append(time.monotonic())

    session = client_session(args)
    reports = 0
    try:
        session.declare_subscriber(full_key(args), on_sample)
        while args.count == 0 or reports < args.count:
            time.sleep(args.window)  # the measurement window itself
            now = time.monotonic()
            with lock:
                recent = [t for t in stamps if t >= now - args.window]
                stamps[:] = recent
            if len(recent) >= 2:
                gaps = [b - a for a, b in zip(recent, recent[1:])]
                mean = sum(gaps) / len(gaps)
                print(f"average rate: {1.0 / mean:.2f} Hz  min {min(gaps) * 1e3:.1f} ms  max {max(gaps) * 1e3:.1f} ms"
                      f"  window {len(recent)}", flush=True)
            else:
                print(f"average rate: {len(recent) / args.window:.2f} Hz (fewer than 2 messages)", flush=True)
            reports += 1
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    return 0
