"""Zenoh session factory: router, peer or client on explicit endpoints, multicast scouting off.

The data path is rmw_zenoh's: services are peers that connect to the router and listen on an ephemeral loopback
port (``tcp/127.0.0.1:0``), or, opt-in, on a unix socket of their own (``peer_socket_dir``: no TCP port for the
kernel to hand out). It is not ``zagv up``'s default: a unix socket buffers far less than loopback TCP, and at a
load average of 33 a recorder lost 2 of 2060 scans (published with congestion control DROP) that it received in
full over TCP. The router tells each peer, by gossip over the links it already has (never multicast), where the
others listen, and the peers then exchange data directly (one socket hop instead of two, no router process in
between). The router stays the rendezvous for discovery, for clients (command-line tools, remote hosts
over TLS, which its access control governs) and for liveliness. A router config must therefore keep gossip on
(deploy/zenoh/*.json5); with it off, peers would not find each other.

Large payloads (map, costmap, particles, above ``transport/shared_memory/transport_optimization/
message_size_threshold``) travel through POSIX shared memory between peers of one host: zenoh copies them into its
SHM pool and sends a reference, negotiated per link, falling back to the socket when the other side cannot map the
segment (another user, a private /dev under systemd). When ``/dev/shm`` is not writable here, SHM is switched off at
once (:func:`shm_usable`). Each process that publishes such payloads has its own pool, resident in full in every
process that maps it, so the pool is ``SHM_POOL_BYTES`` (zenoh's default is 16 MiB) unless a config sets it: a
payload that finds no room in the pool goes over the socket instead.
"""

from __future__ import annotations

import json
import os
import secrets

import zenoh

from services.common.settings import ZenohSettings

#: where a peer listens when its settings name no endpoint: loopback, a port the kernel picks
PEER_LISTEN_DEFAULT = "tcp/127.0.0.1:0"
#: sun_path of struct sockaddr_un holds 108 bytes with the terminating NUL
UNIX_PATH_MAX = 107
SHM_DIR = "/dev/shm"
SHM_POOL_KEY = "transport/shared_memory/transport_optimization/pool_size"
#: each process's zenoh SHM pool: room for several corridor-sized maps or costmaps (a 640 x 350 grid is 224 kB) in
#: flight. The pool is resident in every process that maps it (measured: 16 MB per pool and reader with zenoh's
#: 16 MiB default), so its size multiplies by the readers of map, costmap and particles
SHM_POOL_BYTES = 2 * 1024 * 1024
#: zenoh's thread pools for a service (``ZENOH_RUNTIME``, read once when the process first uses zenoh; a value in the
#: environment wins): one thread receiving instead of zenoh's two. A service has two or three links (the router and
#: the peers it exchanges data with) carrying at most a few hundred messages a second, which one thread receives at
#: the same latency; the second one only added wake-ups (measured per thread: docs/performance.md)
SERVICE_RUNTIME = "(rx: (worker_threads: 1))"
#: ``connect/retry`` unless a config sets it: redial a lost endpoint after 0.1 s, backing off to 0.5 s at most
RECONNECT_RETRY = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}


def _zenoh_default(conf: zenoh.Config, key: str) -> bool:
    """Whether ``key`` of ``conf`` still has zenoh's default value."""
    return bool(conf.get_json(key) == zenoh.Config().get_json(key))


def shm_usable(path: str) -> bool:
    """Whether POSIX shared memory can be created here (zenoh's SHM pool lives in ``/dev/shm``)."""
    return os.path.isdir(path) and os.access(path, os.W_OK | os.X_OK)


def peer_socket(folder: str) -> str:
    """A unix-socket endpoint of this process in ``folder``: ``unixsock-stream/<folder>/<pid>-<random>.sock``.

    The name is new for every session (a restarted service never meets its predecessor's file); zenoh removes the
    socket when the session closes; the folder's owner removes what a killed process left."""
    path = os.path.join(os.path.abspath(folder), f"{os.getpid()}-{secrets.token_hex(4)}.sock")
    if len(path.encode()) > UNIX_PATH_MAX:
        raise ValueError(f"zenoh.peer_socket_dir {folder!r}: a socket path there ({len(path.encode())} bytes) is "
                         f"longer than the {UNIX_PATH_MAX} bytes a unix socket address holds")
    return f"unixsock-stream/{path}"


def zenoh_config(settings: ZenohSettings) -> zenoh.Config:
    """A zenoh.Config for ``settings``; scouting by UDP multicast is disabled in every mode."""
    conf = zenoh.Config.from_file(settings.config_file) if settings.config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if settings.connect and settings.mode != "router":
        conf.insert_json5("connect/endpoints", json.dumps(settings.connect))
    if settings.mode == "router":
        dial = [e for e in settings.connect if e not in settings.listen] if settings.listen else []
        if dial or not settings.config_file:  # a config file's connect list (a robot's site router) stays
            conf.insert_json5("connect/endpoints", json.dumps(dial))
    if settings.listen:
        conf.insert_json5("listen/endpoints", json.dumps(settings.listen))
    elif settings.mode == "peer":
        # reachable by the other peers of this host only, never on another interface
        listen = peer_socket(settings.peer_socket_dir) if settings.peer_socket_dir else PEER_LISTEN_DEFAULT
        conf.insert_json5("listen/endpoints", json.dumps([listen]))
    elif settings.mode == "router":
        # a router listens only where told to; never on every interface by default
        conf.insert_json5("listen/endpoints", json.dumps([]))
    if settings.mode != "client" and json.loads(conf.get_json("scouting/gossip/enabled")) is None:
        # gossip over existing links only (no multicast): the router passes on where peers listen, peers dial
        # each other; the router itself dials no one. A config file that sets gossip keeps its choice.
        conf.insert_json5("scouting/gossip", json.dumps(
            {"enabled": True, "multihop": False, "autoconnect": {"router": [], "peer": ["router", "peer"]}}))
    if not shm_usable(SHM_DIR):
        conf.insert_json5("transport/shared_memory/enabled", "false")
    elif _zenoh_default(conf, SHM_POOL_KEY):  # a pool size set by a config file stays
        conf.insert_json5(SHM_POOL_KEY, str(SHM_POOL_BYTES))
    # extra json5 keys ([zenoh.options] table, then $ZAGV_ZENOH_OPTIONS as a JSON object for a whole stack)
    extra = dict(settings.options)
    extra.update(json.loads(os.environ.get("ZAGV_ZENOH_OPTIONS", "{}")))
    for key, value in extra.items():
        if key.startswith("scouting/multicast"):
            raise ValueError(f"zenoh option {key!r}: multicast scouting stays off (explicit endpoints only)")
        conf.insert_json5(key, json.dumps(value))
    if settings.mode == "client":
        # keep retrying the router forever rather than failing at start when it is not up yet
        conf.insert_json5("connect/timeout_ms", "-1")
        conf.insert_json5("connect/exit_on_failure", "false")
    if json.loads(conf.get_json("connect/retry")) is None:
        # after a lost link, dial again every RECONNECT_RETRY period (zenoh's default backs off to 4 s): a site
        # view is back within about a second of its router's return
        conf.insert_json5("connect/retry", json.dumps(RECONNECT_RETRY))
    return conf


def open_session(settings: ZenohSettings) -> zenoh.Session:
    """Open a zenoh session for ``settings``; a peer or client process gets zenoh's thread pools of
    ``SERVICE_RUNTIME`` unless ``ZENOH_RUNTIME`` is set."""
    if settings.mode != "router":
        os.environ.setdefault("ZENOH_RUNTIME", SERVICE_RUNTIME)
    return zenoh.open(zenoh_config(settings))


def router_settings(listen: list[str]) -> ZenohSettings:
    """Settings of the embedded router listening on ``listen`` (loopback by default)."""
    return ZenohSettings(mode="router", connect=[], listen=listen)
