"""The asyncio bridge against a real router on loopback: typed pub/sub, bad payloads, queries, latching."""

from __future__ import annotations

import asyncio
import threading
import time

import pytest
import zenoh

from proto import Keys, encode
from proto.messages import Empty, LaserScan, OccupancyGrid, Pose2D, Reply, Twist2D
from services.common.node import Node
from services.common.query import NoAnswer, QueryError
from services.common.session import open_session
from services.common.settings import ZenohSettings
from tests.support.stack import free_port
from tests.support.waiting import wait_for


@pytest.fixture
def client(router):
    sessions = []

    def make():
        s = open_session(ZenohSettings(connect=[router]))
        sessions.append(s)
        return s

    yield make
    for s in sessions:
        s.close()


async def test_typed_pubsub_and_bad_payload_is_counted(client):
    keys = Keys("t1")
    a = Node("a", client(), keys)
    b = Node("b", client(), keys)
    got: list[Twist2D] = []
    b.subscribe("cmd_vel", got.append)
    pub = a.publisher("cmd_vel")
    raw = a.session.declare_publisher(keys("cmd_vel"))
    await wait_for(lambda: (pub.put(Twist2D(vx=0.1)), bool(got))[1], timeout_s=5)
    raw.put(b"\xc1 not msgpack")
    raw.put(encode(Pose2D(x=1.0)))
    await wait_for(lambda: b.bad_payloads[keys("cmd_vel")] == 2, timeout_s=5)
    n = len(got)
    pub.put(Twist2D(vx=0.2))
    await wait_for(lambda: len(got) > n and got[-1].vx == 0.2, timeout_s=5)
    a.close()
    b.close()


async def test_query_reply_and_errors(client):
    keys = Keys("t2")
    server = Node("srv", client(), keys)
    caller = Node("cli", client(), keys)

    async def enable(req: Empty) -> Reply:
        await asyncio.sleep(0)
        return Reply(ok=True, message="enabled")

    def boom(req: Empty) -> Reply:
        raise RuntimeError("controller offline")

    server.queryable("drive/enable", enable)
    server.queryable("drive/estop", boom)
    reply = await wait_for_reply(caller, "drive/enable")
    assert reply == Reply(ok=True, message="enabled")
    reply = await caller.query("drive/estop", timeout_s=10.0)  # generous: a loaded machine delays the reply
    assert not reply.ok and "controller offline" in reply.message
    with pytest.raises(QueryError):
        await caller.query("drive/release", timeout_s=0.3)
    server.close()
    caller.close()


async def wait_for_reply(node: Node, name: str):
    last: Exception | None = None
    for _ in range(50):
        try:
            return await node.query(name, timeout_s=0.5)
        except QueryError as exc:
            last = exc
    raise AssertionError(f"no reply: {last}")


async def test_latched_topic_reaches_late_joiner(client):
    keys = Keys("t3")
    pub_node = Node("map_server", client(), keys)
    pub = pub_node.publisher("map", latched=True)
    pub.put(OccupancyGrid(width=2, height=1, data=bytes([0, 100])))
    late = Node("late", client(), keys)
    got: list[OccupancyGrid] = []
    await wait_for(lambda: (got or late.subscribe("map", got.append, latched=True)) and bool(got), timeout_s=5,
                   poll_s=0.5)
    assert got[0].width == 2
    pub_node.close()
    late.close()


async def test_query_waits_for_a_queryable_that_appears_late(client):
    keys = Keys("t4")
    caller = Node("cli", client(), keys)
    server = Node("srv", client(), keys)

    async def declare_later() -> None:
        await asyncio.sleep(0.5)  # the answerer comes after the question was asked
        server.queryable("drive/enable", lambda req: Reply(ok=True, message="enabled"))

    task = asyncio.get_running_loop().create_task(declare_later())
    reply = await caller.query("drive/enable", timeout_s=30.0)
    assert reply.ok and task.done()
    server.close()
    caller.close()


async def test_query_error_names_the_key_and_the_real_wait(client):
    caller = Node("cli", client(), Keys("t5"))
    t0 = asyncio.get_running_loop().time()
    with pytest.raises(NoAnswer) as err:
        await caller.query("drive/enable", timeout_s=0.8)
    waited = asyncio.get_running_loop().time() - t0
    assert waited >= 0.8 and err.value.attempts > 1
    assert "agv/t5/drive/enable" in str(err.value) and "no queryable answered" in str(err.value)
    assert f"waited {err.value.waited_s:.1f} s" in str(err.value) and err.value.waited_s >= 0.75
    caller.close()


async def test_a_queryable_too_slow_for_the_deadline_is_no_answer_not_an_error_reply(client):
    """Zenoh ends a get whose timeout ran out with an error reply "Timeout": that is a missing answer (NoAnswer,
    the queryable matched), not the service's refusal, so callers that retry on NoAnswer retry it."""
    keys = Keys("t5b")
    caller = Node("cli", client(), keys)
    server = Node("srv", client(), keys)

    async def slow(_: Empty) -> Reply:
        await asyncio.sleep(1.5)
        return Reply(ok=True, message="late")

    server.queryable("drive/enable", slow)
    with pytest.raises(NoAnswer) as err:
        await caller.query("drive/enable", timeout_s=0.6)
    assert "a queryable matched but sent no reply" in str(err.value)
    server.close()
    caller.close()


async def test_latched_topic_reaches_early_joiner_and_survives_a_producer_restart(client):
    keys = Keys("t6")
    consumer = Node("consumer", client(), keys)
    got: list[OccupancyGrid] = []
    consumer.subscribe("map", got.append, latched=True)  # before any producer exists
    for width in (2, 3):  # a producer, then its restart with a new value
        producer = Node("map_server", client(), keys)
        pub = producer.publisher("map", latched=True)
        # published before the consumer's link to it is known: only the fetch on appearance can deliver it
        pub.put(OccupancyGrid(width=width, height=1, data=bytes(width)))
        await wait_for(lambda w=width: got and got[-1].width == w, timeout_s=10)
        producer.close()
        producer.session.close()
    consumer.close()


async def test_health_token_only_once_ready(client):
    keys = Keys("t7")
    observer = client()
    node = Node("drive", client(), keys)

    def alive() -> bool:
        return any(r.ok is not None for r in observer.liveliness().get(keys.health("drive"), timeout=0.5))

    node.queryable("drive/enable", lambda req: Reply(ok=True))
    assert not alive(), "a health token before the service said it is ready"
    node.ready("CAN link up")
    await wait_for(alive, timeout_s=10, poll_s=0.1)
    node.close()


async def test_a_large_latched_message_published_once_after_a_slow_start_arrives(client):
    keys = Keys("t8")
    consumer = Node("nav", client(), keys)
    got: list[OccupancyGrid] = []
    consumer.subscribe("map", got.append, latched=True)
    producer = Node("localization", client(), keys)
    pub = producer.publisher("map", latched=True)  # the queryable appears with nothing to serve yet
    await asyncio.sleep(1.0)  # the producer loading its map: the consumer's fetch found no value
    pub.put(OccupancyGrid(width=640, height=350, data=bytes(640 * 350)))  # once, 224 kB: must not be dropped
    await wait_for(lambda: got and got[-1].width == 640, timeout_s=10)
    producer.close()
    consumer.close()


def _hold_the_loop(seconds: float) -> None:
    """Keep the calling thread (the event loop's) busy in Python bytecode, as a long synchronous step does."""
    until = time.monotonic() + seconds
    while time.monotonic() < until:
        sum(i * i for i in range(2000))


async def test_a_blocked_loop_still_gets_every_message_in_order_and_latest_only_stays_latest(client):
    """While the loop is held for 2 s, 300 scans are published: ``subscribe`` (and an unbounded ``subscription``)
    hand over all of them, in order, once the loop turns again (the bridge between Zenoh's thread and the loop
    drops nothing); a ``subscription`` with the default ``maxlen=1`` (control topics) yields only the newest."""
    keys = Keys("t_blocked")
    node = Node("b", client(), keys)
    every: list[float] = []
    node.subscribe("scan", lambda m: every.append(m.stamp))
    unbounded = node.subscription("scan", maxlen=None)
    latest = node.subscription("scan")
    pub = client().declare_publisher(keys("scan"), congestion_control=zenoh.CongestionControl.BLOCK)
    probe = LaserScan(stamp=-1.0)
    await wait_for(lambda: (pub.put(encode(probe)), bool(every))[1], timeout_s=10)
    await asyncio.sleep(0.2)  # probes still in flight arrive before the count starts
    every.clear()
    n = 300
    body = b"\0" * (4 * 360)  # an LMS111-sized scan

    def publish() -> None:
        for i in range(n):
            pub.put(encode(LaserScan(stamp=float(i), ranges=body)))

    sender = threading.Thread(target=publish)
    sender.start()
    _hold_the_loop(2.0)
    sender.join()
    await wait_for(lambda: len(every) >= n, timeout_s=20, message=f"all {n} scans after the loop was held")
    assert every == [float(i) for i in range(n)]
    assert node.received[keys("scan")] == node.delivered[keys("scan")] >= n
    got: list[float] = []
    async for msg in unbounded:
        if msg.stamp >= 0:
            got.append(msg.stamp)
        if len(got) == n:
            break
    assert got == every
    newest = await asyncio.wait_for(anext(latest), 5.0)
    assert newest.stamp == n - 1  # only the newest of the backlog was kept
    node.close()


def test_wait_listening_returns_once_a_port_takes_connections_and_names_a_dead_one() -> None:
    import socket

    from services.common.ports import free_port, wait_listening

    listening = free_port()
    with socket.create_server(("127.0.0.1", listening)):
        wait_listening(listening, timeout_s=5.0)
    port = free_port()
    with pytest.raises(TimeoutError, match=f"127.0.0.1:{port} within 0.2 s"):
        wait_listening(port, timeout_s=0.2)


async def test_a_stuck_subscriber_never_makes_a_peer_publisher_wait() -> None:
    """Peers (no router between them): the subscribing node's reader is stuck, as one waiting for the GIL is, while
    2000 messages of 20 kB are published with congestion control BLOCK. The publisher gets through all of them
    (the subscriber's native ring drops its own oldest samples; Zenoh's thread never waits for the reader), and
    once the reader turns again it gets the newest. With a queue that blocks when full (zenoh's default behind a
    Python callback), the puts wait for the stuck process and the link is closed (docs/performance.md)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sub_session = open_session(ZenohSettings(mode="peer", connect=[], listen=[endpoint]))
    pub_session = open_session(ZenohSettings(mode="peer", connect=[endpoint]))
    try:
        await wait_for(lambda: list(pub_session.info.peers_zid()), timeout_s=20, message="the peers never met")
        keys = Keys("t_stuck")
        node = Node("stuck", sub_session, keys)
        gate = threading.Event()
        seen: list[float] = []

        def stuck(msg: LaserScan) -> None:
            seen.append(msg.stamp)
            gate.wait()  # the reader thread stays here until released

        node.subscribe("scan", stuck, on_zenoh_thread=True)
        pub = pub_session.declare_publisher(keys("scan"), congestion_control=zenoh.CongestionControl.BLOCK)
        await wait_for(lambda: (pub.put(encode(LaserScan(stamp=-1.0))), bool(seen))[1], timeout_s=20,
                       message="the subscriber never got a message")
        n = 2000
        body = b"\0" * 20_000
        done = threading.Event()

        def publish() -> None:
            for i in range(n):
                pub.put(encode(LaserScan(stamp=float(i), ranges=body)))
            done.set()

        sender = threading.Thread(target=publish, daemon=True)
        sender.start()
        try:
            await wait_for(done.is_set, timeout_s=60, poll_s=0.05,
                           message="the publisher waited for the stuck subscriber")
        finally:
            gate.set()
        await wait_for(lambda: seen[-1] == n - 1, timeout_s=20, message="the newest message never arrived")
        key = keys("scan")
        assert node.received[key] < n  # the ring dropped the stuck reader's oldest samples
        assert seen == sorted(seen)
        node.close()
    finally:
        gate.set()
        pub_session.close()
        sub_session.close()
