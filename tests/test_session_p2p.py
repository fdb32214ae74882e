"""The rmw_zenoh data path: peers find each other through the router, then exchange data directly.

A real router process (``zagv router``, with the deployed loopback config or the built-in settings ``zagv up``
embeds) and peer sessions as the services open them; "directly" is shown by the data still flowing after the
router is killed.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import msgspec
import pytest
import zenoh

from services.common.session import PEER_LISTEN_DEFAULT, open_session, shm_usable, zenoh_config
from services.common.settings import ZenohSettings
from tests.support.stack import free_port
from tests.support.waiting import wait_for_sync

REPO_ROOT = Path(__file__).resolve().parents[1]


def make_socket_dir() -> str:
    """A private folder short enough for unix socket paths (pytest's tmp_path can be longer than 107 bytes)."""
    return tempfile.mkdtemp(prefix="zagv-z", dir="/tmp")


def test_peer_defaults_listen_on_loopback_only_and_gossip_without_multicast() -> None:
    conf = zenoh_config(ZenohSettings(mode="peer", connect=["tcp/127.0.0.1:7447"]))
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("listen/endpoints")) == [PEER_LISTEN_DEFAULT]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is True
    assert json.loads(conf.get_json("scouting/gossip/multihop")) is False
    router = zenoh_config(ZenohSettings(mode="router", connect=[], listen=["tcp/127.0.0.1:7447"]))
    assert json.loads(router.get_json("scouting/gossip"))["autoconnect"]["router"] == []


def test_shared_memory_falls_back_where_dev_shm_is_not_writable(tmp_path: Path, monkeypatch) -> None:
    assert not shm_usable(str(tmp_path / "missing"))
    monkeypatch.setattr("services.common.session.SHM_DIR", str(tmp_path / "missing"))
    conf = zenoh_config(ZenohSettings(mode="peer", connect=["tcp/127.0.0.1:7447"]))
    assert json.loads(conf.get_json("transport/shared_memory/enabled")) is False


def test_a_peer_socket_folder_gives_each_session_a_unix_socket_of_its_own(tmp_path: Path) -> None:
    settings = ZenohSettings(mode="peer", connect=["tcp/127.0.0.1:7447"], peer_socket_dir=str(tmp_path))
    first, second = (json.loads(zenoh_config(settings).get_json("listen/endpoints")) for _ in range(2))
    assert first[0].startswith(f"unixsock-stream/{tmp_path}/") and first[0].endswith(".sock")
    assert first != second  # a restarted service never meets the socket file its predecessor left
    with pytest.raises(ValueError, match="longer than the 107 bytes"):
        zenoh_config(msgspec.structs.replace(settings, peer_socket_dir=str(tmp_path / ("x" * 100))))


@pytest.mark.integration
@pytest.mark.parametrize(("transport", "router_config"), [("tcp", None), ("tcp", "deploy/zenoh/router-loopback.json5"),
                                                          ("unix", None)])
def test_peers_exchange_data_directly_and_keep_going_without_the_router(transport: str, router_config: str | None,
                                                                        ) -> None:
    """``tcp``: peers as the systemd units run them; ``unix``: as ``zagv up`` runs them (the router's and each
    peer's unix socket in one folder)."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    socket_dir = make_socket_dir()
    router_socket = f"unixsock-stream/{socket_dir}/router.sock"
    args = [sys.executable, "-m", "services.cli", "router", "--listen", endpoint]
    if transport == "unix":
        args += ["--listen", router_socket]
    if router_config:
        args += ["--config", str(REPO_ROOT / router_config)]
    router = subprocess.Popen(args, cwd=REPO_ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, start_new_session=True)
    peer = ZenohSettings(mode="peer", connect=[endpoint]) if transport == "tcp" else \
        ZenohSettings(mode="peer", connect=[router_socket], peer_socket_dir=socket_dir)
    sessions: list[zenoh.Session] = []
    try:
        a = open_session(peer)
        b = open_session(peer)
        sessions += [a, b]
        wait_for_sync(lambda: str(b.info.zid()) in {str(z) for z in a.info.peers_zid()}, timeout_s=20,
                      message="the two peers never connected to each other")
        got: list[bytes] = []
        lock = threading.Lock()

        def on_sample(sample: zenoh.Sample) -> None:
            with lock:
                got.append(sample.payload.to_bytes())

        b.declare_subscriber("zagv-test/p2p", on_sample)
        big = os.urandom(200_000)  # above the shared-memory threshold
        pub = a.declare_publisher("zagv-test/p2p")

        def arrived(payload: bytes) -> bool:
            pub.put(payload)
            with lock:
                return payload in got

        wait_for_sync(lambda: arrived(b"before"), timeout_s=20, poll_s=0.1, message="no data through the peers")
        wait_for_sync(lambda: arrived(big), timeout_s=20, poll_s=0.1, message="a large payload never arrived")
        os.killpg(router.pid, signal.SIGKILL)
        router.wait(10)
        wait_for_sync(lambda: arrived(b"after the router died"), timeout_s=20, poll_s=0.1,
                      message="data stopped with the router: it was not peer-to-peer")
        if transport == "unix":
            # the peers' own sockets: the data path took no TCP port
            assert len(list(Path(socket_dir).glob("*-*.sock"))) == 2
    finally:
        for s in sessions:
            s.close()
        if router.poll() is None:
            os.killpg(router.pid, signal.SIGKILL)
            router.wait()
        shutil.rmtree(socket_dir, ignore_errors=True)


def _zenoh_threads(env: dict[str, str], router: str) -> list[str]:
    """The zenoh runtime threads of a fresh process whose session is linked to ``router``."""
    script = (
        "import os, sys, time\n"
        "from services.common.session import open_session\n"
        "from services.common.settings import ZenohSettings\n"
        "s = open_session(ZenohSettings(connect=[sys.argv[1]]))\n"
        "deadline = time.monotonic() + 10\n"
        "names = []\n"
        "while time.monotonic() < deadline:\n"
        "    names = [open(f'/proc/self/task/{t}/comm').read().strip() for t in os.listdir('/proc/self/task')]\n"
        "    if any(n.startswith('rx-') for n in names):\n"
        "        break\n"
        "    time.sleep(0.05)\n"
        "print(' '.join(sorted(n for n in names if n.startswith(('rx-', 'tx-')))))\n")
    result = subprocess.run([sys.executable, "-c", script, router], capture_output=True, text=True, timeout=60,
                            env=env, cwd=REPO_ROOT)
    assert result.returncode == 0, result.stderr
    return result.stdout.split()


def test_a_service_session_receives_on_one_zenoh_thread_unless_the_environment_says_otherwise(router):
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    env["PYTHONPATH"] = str(REPO_ROOT)
    assert [n for n in _zenoh_threads(env, router) if n.startswith("rx-")] == ["rx-0"]
    wider = _zenoh_threads({**env, "ZENOH_RUNTIME": "(rx: (worker_threads: 3))"}, router)
    assert [n for n in wider if n.startswith("rx-")] == ["rx-0", "rx-1", "rx-2"]
