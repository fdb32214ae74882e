"""The asyncio bridge between a service and Zenoh.

Zenoh delivers samples and queries on its own threads. A subscriber's samples go into a native (Rust) queue of its
own, which Zenoh's thread fills without ever taking the GIL; one reader thread per subscriber blocks in ``recv()``
with the GIL released, decodes each sample and hands the typed message to the service's event loop. The queue is a
ring (the oldest sample goes when it is full), so a process that cannot keep up, for instance because its reader
waits for the GIL, loses its own oldest samples and never makes a publisher wait (docs/performance.md, "Zenoh data
path": as peers, a publisher's ``put`` waits for a subscribing process whose queue blocks).

Every payload is checked against the type its key carries (``proto.registry``); a payload
that does not decode is logged (rate-limited), counted in ``bad_payloads`` and dropped, and the service keeps
running. Latched topics (``map``, ``pose``, ``nav/status``, ...) are served to late joiners by a queryable on the
same key, which latched subscribers query whenever such a queryable appears (``LatchedFetch``).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, TypeVar, cast

import msgspec
import zenoh

from proto import codec
from proto.keys import Keys
from proto.messages import Message, Reply
from services.common import systemd
from services.common.clock import Clock, SimClock, WallClock
from services.common.query import QueryError as QueryError  # re-exported for callers
from services.common.query import query

T = TypeVar("T", bound=Message)
log = logging.getLogger("zagv.node")

#: samples a subscriber's native ring holds while its reader thread is away: a reader that waits for the GIL takes
#: one sample per switch interval (5 ms) from a busy process, so about 5 s of a 200 Hz topic. (zenoh's own queue
#: behind a Python callback is a 256-deep FIFO that blocks Zenoh's thread, and through it the publisher, when full)
SUBSCRIBER_QUEUE = 1024
#: the native queue of a keep-every-message subscription (``maxlen=None``): a FIFO, which makes the publisher wait
#: rather than lose a message once this many are unread (a process stalled that long is about to be restarted)
KEEP_ALL_QUEUE = 4096


def _pump(handler: Any, on_item: Callable[[Any], None], what: str) -> None:
    """A reader thread: take items from a native Zenoh queue (``recv`` releases the GIL while it waits) until
    its declaration is undeclared or its session closed."""
    for item in handler:
        try:
            on_item(item)
        except Exception:  # the reader must outlive a bad sample
            log.exception("reader of %s failed", what)


def declare_reader(session: zenoh.Session, key: str, on_sample: Callable[[zenoh.Sample], None],
                   queue: int | None = SUBSCRIBER_QUEUE) -> zenoh.Subscriber[Any]:
    """A subscriber on ``key`` whose samples wait in a native queue (a ring of ``queue`` samples; ``None``: a FIFO
    of ``KEEP_ALL_QUEUE``) and reach ``on_sample`` on a reader thread of their own, never on Zenoh's thread."""
    handler: Any = zenoh.handlers.FifoChannel(KEEP_ALL_QUEUE) if queue is None else \
        zenoh.handlers.RingChannel(max(1, queue))
    sub = session.declare_subscriber(key, handler)
    # the thread holds the handler only, not the subscriber: undeclaring (or dropping) the subscriber ends it
    threading.Thread(target=_pump, args=(sub.handler, on_sample, key), name=f"zagv-sub {key}",
                     daemon=True).start()
    return sub


class SharedReader:
    """One native subscriber and reader thread for every node of a process that subscribes to the same key: the
    services of a container (services/launch/container.py) then pay one reader-thread wake-up per message instead
    of one each (the clock's 100 Hz reaches five services there). Listeners that asked for rings of different
    depths share the deepest (a "newest only" listener of depth 1 is served by a deeper ring: it still ends on the
    newest message); a keep-every-message FIFO (``queue`` None) is a reader of its own. A process with one node has
    one listener per reader, as before."""

    _registry: dict[tuple[int, str, bool], SharedReader] = {}
    _lock = threading.Lock()

    def __init__(self, session: zenoh.Session, key: str, queue: int | None,
                 listeners: tuple[Callable[[zenoh.Sample], None], ...] = ()) -> None:
        self.registry_key = (id(session), key, queue is None)
        self.session = session  # held: while the reader lives, no other session can take this id()
        self.queue = queue
        self.listeners = listeners
        self.subscriber = declare_reader(session, key, self._on_sample, queue)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        for listener in self.listeners:
            try:
                listener(sample)
            except Exception:
                log.exception("a listener of %s failed", self.registry_key[1])

    @classmethod
    def listen(cls, session: zenoh.Session, key: str, on_sample: Callable[[zenoh.Sample], None],
               queue: int | None = SUBSCRIBER_QUEUE) -> ReaderLease:
        """Add ``on_sample`` to the process's reader of ``key`` (declared on first use, or again deeper when this
        listener asks for a deeper ring than it has); undeclare the lease to leave it (the last one out undeclares
        the subscriber)."""
        registry_key = (id(session), key, queue is None)
        replaced = None
        with cls._lock:
            reader = cls._registry.get(registry_key)
            if reader is not None and reader.session.is_closed():  # left behind by a session closed under it
                reader = None
            if reader is not None and queue is not None and reader.queue is not None and queue > reader.queue:
                # a deeper ring takes over every listener; the shallow one is undeclared once it has none
                replaced, reader = reader, cls(session, key, queue, reader.listeners)
                replaced.listeners = ()
                cls._registry[registry_key] = reader
            elif reader is None:
                reader = cls._registry[registry_key] = cls(session, key, queue)
            reader.listeners = (*reader.listeners, on_sample)  # replaced whole: the reader thread iterates a tuple
        if replaced is not None:
            replaced.subscriber.undeclare()
        return ReaderLease(registry_key, on_sample)

    @classmethod
    def leave(cls, registry_key: tuple[int, str, bool], on_sample: Callable[[zenoh.Sample], None]) -> None:
        """Remove ``on_sample`` from the reader that now serves ``registry_key`` (it may have been re-declared
        deeper since the listener joined); the last one out undeclares it."""
        with cls._lock:
            reader = cls._registry.get(registry_key)
            if reader is None:
                return
            reader.listeners = tuple(f for f in reader.listeners if f is not on_sample)
            if reader.listeners:
                return
            del cls._registry[registry_key]
        reader.subscriber.undeclare()


class ReaderLease:
    """A node's place among the listeners of a key's SharedReader."""

    def __init__(self, registry_key: tuple[int, str, bool], on_sample: Callable[[zenoh.Sample], None]) -> None:
        self.registry_key, self.on_sample = registry_key, on_sample

    def undeclare(self) -> None:
        SharedReader.leave(self.registry_key, self.on_sample)


class TopicPublisher:
    """Publishes one topic's messages; keeps the last one for late joiners when latched."""

    def __init__(self, node: Node, name: str, latched: bool, express: bool, block: bool | None = None) -> None:
        self.key = node.keys(name)
        # latched state is published rarely and must arrive: block rather than drop under congestion (Zenoh's
        # default drops, and a large message such as the map, sent once, would then be lost for good)
        block = latched if block is None else block
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._pub = node.session.declare_publisher(self.key, express=express, congestion_control=congestion)
        self._last: bytes | None = None
        self._queryable = None
        if latched:
            self._queryable = node.session.declare_queryable(self.key, self._serve_last, complete=False)

    def _serve_last(self, query: zenoh.Query) -> None:
        if self._last is not None:
            query.reply(self.key, self._last)

    def put(self, msg: Message) -> None:
        payload = codec.encode(msg)
        if self._queryable is not None:
            self._last = payload
        self._pub.put(payload)

    def put_raw(self, payload: bytes) -> None:
        self._pub.put(payload)

    def close(self) -> None:
        self._pub.undeclare()
        if self._queryable is not None:
            self._queryable.undeclare()


class LatchedFetch:
    """Fetches a latched topic's last value whenever a publisher's queryable for it appears, in any start order.

    A Zenoh querier's matching listener reports when a queryable on the key comes (a producer started or
    restarted, before or after this consumer); each time, the last value is asked for once. Values published
    after the consumer's subscriber exists arrive through the subscriber itself.
    """

    def __init__(self, session: zenoh.Session, key: str, on_sample: Callable[[zenoh.Sample], None]) -> None:
        self._on_sample = on_sample
        self.fetches = 0
        self._querier = session.declare_querier(key, timeout=5.0, consolidation=zenoh.ConsolidationMode.NONE)
        self._listener = self._querier.declare_matching_listener(self._on_matching)
        if self._querier.matching_status.matching:  # type: ignore[attr-defined]  # a MatchingStatus, not bool
            self._fetch()

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        if status.matching:
            self._fetch()

    def _fetch(self) -> None:
        self.fetches += 1
        self._querier.get(zenoh.handlers.Callback(self._on_reply, lambda: None))

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._on_sample(reply.ok)

    def undeclare(self) -> None:
        self._listener.undeclare()
        self._querier.undeclare()


class Node:
    """A service's Zenoh presence: typed pub/sub and queries on its loop, a clock and a health token."""

    def __init__(self, name: str, session: zenoh.Session, keys: Keys, clock: Clock | None = None) -> None:
        self.name = name
        self.session = session
        self.keys = keys
        self.clock: Clock = clock or WallClock()
        self.loop = asyncio.get_running_loop()
        self.log = logging.getLogger(f"zagv.{name}")
        self.bad_payloads: collections.Counter[str] = collections.Counter()
        # per key: samples the reader threads took from the native queues and messages the loop delivered (the
        # bridge's two ends)
        self.received: collections.Counter[str] = collections.Counter()
        self.delivered: collections.Counter[str] = collections.Counter()
        self._bad_logged_at: dict[str, float] = {}
        self._declared: list[Any] = []
        self._started_at = time.monotonic()
        self._token: Any = None  # the health token: declared by ready()
        self.ready_at: float | None = None
        #: tells the service manager the service is ready (systemd READY=1); a container counts its services
        self.notify_ready: Callable[[], None] = _notify_systemd_ready
        self._stats = session.declare_queryable(keys(f"@stats/{name}"), self._serve_stats)
        self.extra_stats: dict[str, Any] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        # messages for the loop, posted by the reader threads; one loop wake-up serves every message that arrived
        # before the loop came round to them (``_post``)
        self._inbox: collections.deque[tuple[Callable[[Any], None], Any]] = collections.deque()
        self._drain_scheduled = False
        self.loop_wakeups = 0  # drains the reader threads scheduled: event-loop wake-ups for messages
        #: called on the clock's reader thread with each sim time stamp in s (a service's own thread-side ticker
        #: rides on the node's one clock subscription instead of declaring a second one)
        self.clock_listeners: list[Callable[[float], None]] = []
        if isinstance(self.clock, SimClock):
            sim_clock = self.clock
            sim_clock.bind(self.loop)
            listeners = self.clock_listeners

            def on_clock(c: Any) -> None:
                sim_clock.advance_threadsafe(c.stamp, c.speed_factor)
                for listener in listeners:
                    listener(c.stamp)

            # on the reader thread: the loop is woken only when a sleeper is due (SimClock.advance_threadsafe)
            self.subscribe("clock", on_clock, on_zenoh_thread=True, queue=1)

    def ready(self, inputs: str = "") -> None:
        """Declare the health token and tell systemd READY=1 (idempotent).

        Call it once every subscriber, queryable and publisher the service offers exists and its required inputs
        are in hand (docs/readiness.md); ``inputs`` says which, for the log.
        """
        if self._token is not None:
            return
        self._token = self.session.liveliness().declare_token(self.keys.health(self.name))
        self.ready_at = time.monotonic()
        self.notify_ready()
        self.log.info("ready after %.1f s%s", self.ready_at - self._started_at, f" ({inputs})" if inputs else "")

    async def ready_when(self, condition: Callable[[], str | None], stop: asyncio.Event, poll_s: float = 0.05,
                         declare: Callable[[], Any] | None = None) -> None:
        """Wait (wall time) until ``condition()`` returns a description of the inputs in hand, then call
        ``declare()`` (queryables that need those inputs to answer) and ``ready``."""
        while not stop.is_set():
            inputs = condition()
            if inputs is not None:
                if declare is not None:
                    declare()
                self.ready(inputs)
                return
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), poll_s)

    def spawn(self, coro: Awaitable[Any]) -> asyncio.Task[Any]:
        """Run ``coro`` as a task on the loop, keeping a reference until it ends (loop thread only)."""
        task: asyncio.Task[Any] = self.loop.create_task(coro)  # type: ignore[arg-type]
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # ------------------------------------------------------------------ diagnostics

    def _serve_stats(self, query: zenoh.Query) -> None:
        stats = {
            "service": self.name,
            "uptime_s": time.monotonic() - self._started_at,
            "bad_payloads": dict(self.bad_payloads),
            "received": dict(self.received),
            "delivered": dict(self.delivered),
            "loop_wakeups": self.loop_wakeups,
            "clock_loop_wakeups": getattr(self.clock, "loop_wakeups", 0),
            "clock_s": self.clock.now(),
            **self.extra_stats,
        }
        # its own key, not the query's (``@stats/*`` from ``zagv status``): replies on one key are consolidated to
        # one, which would keep a single answer from the services of one composed process
        query.reply(self.keys(f"@stats/{self.name}"), msgspec.json.encode(stats))

    def _bad_payload(self, key: str, exc: Exception) -> None:
        self.bad_payloads[key] += 1
        now = time.monotonic()
        if now - self._bad_logged_at.get(key, -math.inf) >= 1.0:
            self._bad_logged_at[key] = now
            self.log.warning("dropped bad payload #%d on %s: %s", self.bad_payloads[key], key, exc)

    def _decoder(self, name: str, t: type[T] | None) -> Callable[[zenoh.Sample], T | None]:
        msg_type = t if t is not None else cast("type[T]", codec.topic_type(name))

        def decode(sample: zenoh.Sample) -> T | None:
            key = str(sample.key_expr)
            try:
                return codec.decode_as(msg_type, sample.payload.to_bytes(), key)
            except codec.ProtoDecodeError as exc:
                self.loop.call_soon_threadsafe(self._bad_payload, key, exc)
                return None

        return decode

    # ------------------------------------------------------------------ pub/sub

    def publisher(self, name: str, *, latched: bool = False, express: bool = False,
                  block: bool | None = None) -> TopicPublisher:
        """A publisher on ``agv/<id>/<name>``; ``latched`` serves the last message to late joiners and (unless
        ``block`` is False: a large periodic message may be dropped) never drops one under congestion."""
        pub = TopicPublisher(self, name, latched, express, block)
        self._declared.append(pub)
        return pub

    def subscribe(
        self,
        name: str,
        callback: Callable[[T], Any],
        *,
        msg_type: type[T] | None = None,
        latched: bool = False,
        on_zenoh_thread: bool = False,
        queue: int | None = SUBSCRIBER_QUEUE,
    ) -> None:
        """Call ``callback(msg)`` for each valid message on ``name``.

        The callback runs on the event loop, or directly on the subscriber's reader thread when ``on_zenoh_thread``
        (for latency-critical consumers that do their own locking; never on Zenoh's own thread). A coroutine
        function is scheduled as a task. With ``latched``, the last message held by a latched publisher is fetched
        once at declaration. ``queue``: the native ring's depth (the oldest sample goes when the reader is that far
        behind); ``None`` keeps every sample (module docstring).
        """
        decode = self._decoder(name, msg_type)
        is_coro = asyncio.iscoroutinefunction(callback)
        key = self.keys(name)

        def deliver(msg: Any) -> None:
            self.delivered[key] += 1
            try:
                if is_coro:
                    self.spawn(callback(msg))
                else:
                    callback(msg)
            except Exception:
                self.log.exception("handler of %s failed", name)

        def on_sample(sample: zenoh.Sample) -> None:
            self.received[key] += 1
            msg = decode(sample)
            if msg is None:
                return
            if on_zenoh_thread and not is_coro:
                self.delivered[key] += 1
                try:
                    callback(msg)
                except Exception:
                    self.log.exception("handler of %s failed", name)
            else:
                self._post(deliver, msg)

        self._declared.append(SharedReader.listen(self.session, key, on_sample, queue))
        if latched:
            self._declared.append(LatchedFetch(self.session, key, on_sample))

    def subscribe_raw(self, name: str, on_sample: Callable[[zenoh.Sample], None]) -> None:
        """Call ``on_sample(sample)`` with each undecoded sample on ``name``, on the key's reader thread (the one the
        process's other subscribers of ``name`` share): for consumers of raw payloads such as the black box."""
        key = self.keys(name)

        def counted(sample: zenoh.Sample) -> None:
            self.received[key] += 1
            on_sample(sample)

        self._declared.append(SharedReader.listen(self.session, key, counted))

    def _post(self, deliver: Callable[[Any], None], msg: Any) -> None:
        """Queue ``deliver(msg)`` for the loop (any reader thread). The loop is woken only when no drain is pending:
        messages that arrive together (a simulator tick's odom, tf and scan) share one wake-up, where each wake-up
        costs a small PC more than the message's own handling. Under the GIL the flag is safe: a reader that still
        sees it set appended its message before the loop cleared it, so that drain takes the message."""
        self._inbox.append((deliver, msg))
        if not self._drain_scheduled:
            self._drain_scheduled = True
            self.loop_wakeups += 1
            try:
                self.loop.call_soon_threadsafe(self._drain)
            except RuntimeError:  # the loop closed (the service is stopping): nothing will read the message
                self._inbox.clear()

    def _drain(self) -> None:
        """Deliver the messages queued when the drain started, in arrival order (loop thread); later ones get a
        drain of their own after the loop has run its other callbacks."""
        self._drain_scheduled = False
        inbox = self._inbox
        for _ in range(len(inbox)):
            deliver, msg = inbox.popleft()
            deliver(msg)

    def subscription(self, name: str, *, maxlen: int | None = 1, **kwargs: Any) -> AsyncIterator[Any]:
        """An async iterator over messages on ``name`` keeping at most ``maxlen`` unread (oldest dropped): the
        default 1 is "latest only", for control topics where a stale message is worse than none; ``None`` keeps
        every message in order however long the consumer is away (a replayed log)."""
        queue: collections.deque[Any] = collections.deque(maxlen=maxlen)
        ready = asyncio.Event()

        def push(msg: Any) -> None:
            queue.append(msg)
            ready.set()

        kwargs.setdefault("queue", maxlen)  # latest only from the native queue on: nothing older is ever delivered
        self.subscribe(name, push, **kwargs)

        async def iterate() -> AsyncIterator[Any]:
            while True:
                await ready.wait()
                while queue:
                    yield queue.popleft()
                ready.clear()

        return iterate()

    # ------------------------------------------------------------------ queries

    def queryable(self, name: str, handler: Callable[[Any], Awaitable[Message] | Message]) -> None:
        """Serve the query ``name``: ``handler(request)`` (sync or async) returns the reply message.

        A request that does not decode gets ``Reply(ok=False, message=...)`` (or an error reply when the query's
        reply type is not Reply); an exception in the handler gets an error reply naming it.
        """
        req_type, rep_type = codec.query_types(name)
        key = self.keys(name)

        def send(query: zenoh.Query, reply: Message) -> None:
            query.reply(key, codec.encode(reply))

        async def run(query: zenoh.Query, request: Message) -> None:
            try:
                result = handler(request)
                send(query, await result if asyncio.iscoroutine(result) else cast(Message, result))
            except Exception as exc:  # the caller gets the reason; the service goes on
                self.log.exception("query %s failed", name)
                if rep_type is Reply:
                    send(query, Reply(ok=False, message=f"{type(exc).__name__}: {exc}"))
                else:
                    query.reply_err(f"{type(exc).__name__}: {exc}".encode())
            finally:
                # finalise now: the logged traceback keeps this frame (and the query) alive, and the caller's
                # consolidated reply would wait for the query's end until its timeout
                query.drop()

        def on_query(query: zenoh.Query) -> None:
            raw = query.payload.to_bytes() if query.payload is not None else b""
            try:
                request = codec.decode_as(req_type, raw, key) if raw else _default_request(req_type, key)
            except codec.ProtoDecodeError as exc:
                self.loop.call_soon_threadsafe(self._bad_payload, key, exc)
                if rep_type is Reply:
                    query.reply(key, codec.encode(Reply(ok=False, message=str(exc))))
                else:
                    query.reply_err(str(exc).encode())
                return
            self.loop.call_soon_threadsafe(lambda: self.spawn(run(query, request)))

        self._declared.append(self.session.declare_queryable(key, on_query))

    async def query(self, name: str, request: Message | None = None, *, timeout_s: float = 2.0) -> Any:
        """``services.common.query.query`` on this node's session: waits for an answerer until ``timeout_s``."""
        return await query(self.session, self.keys, name, request, timeout_s=timeout_s)

    # ------------------------------------------------------------------ lifetime

    def withdraw_health(self) -> None:
        """Undeclare the health token (any thread): the liveness watchdog saw the event loop stop turning."""
        token, self._token = self._token, None
        if token is not None:
            with contextlib.suppress(Exception):
                token.undeclare()

    def restore_health(self) -> None:
        """Declare the health token again after :meth:`withdraw_health` (loop thread); never before ``ready``."""
        if self._token is None and self.ready_at is not None:
            self._token = self.session.liveliness().declare_token(self.keys.health(self.name))

    def close(self) -> None:
        for d in [*reversed(self._declared), self._stats, self._token]:
            if d is None:
                continue
            with contextlib.suppress(Exception):  # already gone with the session
                (d.close if isinstance(d, TopicPublisher) else d.undeclare)()
        self._declared.clear()


def _notify_systemd_ready() -> None:
    systemd.notify("READY=1")


def _default_request(t: type[T], key: str) -> T:
    """The request for an empty query payload: ``t()`` when every field has a default."""
    try:
        return t()
    except TypeError:
        raise codec.ProtoDecodeError(key, t.__name__, "empty payload; this query needs arguments") from None
