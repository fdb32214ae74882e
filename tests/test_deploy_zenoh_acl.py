"""The LAN router config (mutual TLS + access control) on loopback: the HMI's jog and goal pass, no other host's.

Certificates come from ``deploy/zenoh/make-certs.sh`` (openssl) at test time. The router is a real ``zagv router``
process running ``deploy/zenoh/router-lan-tls.json5`` with only its endpoints (free loopback ports) and certificate
paths replaced; the clients use ``deploy/zenoh/client-hmi-tls.json5`` with their own certificate. "Never arrives" is
shown by ordering: after its denied puts the other host publishes a sentinel on the same link and priority, and the
router forwards one link's messages in order, so once the sentinel is in, the denied puts would have been too.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from services.common.session import open_session
from services.common.settings import ZenohSettings
from tests.support.router import RouterProcess
from tests.support.stack import free_port
from tests.support.waiting import wait_for_sync

REPO_ROOT = Path(__file__).resolve().parents[1]
ZENOH_DIR = REPO_ROOT / "deploy" / "zenoh"
MAKE_CERTS = ZENOH_DIR / "make-certs.sh"
SENTINEL_KEY = "zagv-test/sentinel"

pytestmark = pytest.mark.integration


def make_certs(cert_dir: Path) -> None:
    if not shutil.which("openssl") or not shutil.which("sh"):
        pytest.skip("openssl (and sh) are needed to make the test certificates; not found on PATH")
    for args in (["ca"], ["zagv-router", "DNS:localhost", "IP:127.0.0.1"], ["zagv-hmi"], ["zagv-fleet"]):
        subprocess.run(["sh", str(MAKE_CERTS), str(cert_dir), *args], check=True, capture_output=True, timeout=60)


def router_config(cert_dir: Path, tcp_port: int, tls_port: int) -> dict:
    """The deployed LAN router config with test endpoints and certificates, plus one test-only sentinel rule."""
    conf = json.loads(str(zenoh.Config.from_file(str(ZENOH_DIR / "router-lan-tls.json5"))))
    conf["listen"]["endpoints"] = [f"tcp/127.0.0.1:{tcp_port}", f"tls/127.0.0.1:{tls_port}"]
    tls = conf["transport"]["link"]["tls"]
    tls["root_ca_certificate"] = str(cert_dir / "ca.pem")
    tls["listen_certificate"] = str(cert_dir / "zagv-router.pem")
    tls["listen_private_key"] = str(cert_dir / "zagv-router.key")
    acl = conf["access_control"]
    # a key no deployed rule mentions, so that the other host has one path through the router to order against
    acl["rules"].append({"id": "test-sentinel", "permission": "allow", "flows": ["ingress", "egress"],
                         "messages": ["put", "declare_subscriber"], "key_exprs": [SENTINEL_KEY]})
    acl["policies"].append({"id": "test-sentinel", "rules": ["test-sentinel"], "subjects": ["remote"]})
    return conf


def tls_client(cert_dir: Path, name: str, tls_port: int) -> zenoh.Session:
    """A session from the deployed HMI client config, with the certificate ``name`` and the test router's port."""
    conf = zenoh.Config.from_file(str(ZENOH_DIR / "client-hmi-tls.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{tls_port}"]))
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(cert_dir / "ca.pem")))
    conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(cert_dir / f"{name}.pem")))
    conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(cert_dir / f"{name}.key")))
    return zenoh.open(conf)


def local_client(tcp_port: int) -> zenoh.Session:
    """A robot service's session: a peer on plain TCP over loopback, as robot.toml [zenoh] gives it."""
    return open_session(ZenohSettings(mode="peer", connect=[f"tcp/127.0.0.1:{tcp_port}"]))


@pytest.fixture
def acl_router(tmp_path: Path) -> Iterator[tuple[Path, int, int, RouterProcess]]:
    cert_dir = tmp_path / "tls"
    make_certs(cert_dir)
    tcp_port, tls_port = free_port(), free_port()
    config_path = tmp_path / "router.json5"
    config_path.write_text(json.dumps(router_config(cert_dir, tcp_port, tls_port), indent=1))
    router = RouterProcess(["--config", str(config_path)]).start()
    try:
        wait_for_sync(lambda: any("listening on" in line for line in router.lines) or not router.running(),
                      timeout_s=30, message="router did not start")
        assert router.running(), f"router exited:\n{router.output()}"
        assert f"tls/127.0.0.1:{tls_port}" in router.output(), "router ignored the config file's endpoints"
        yield cert_dir, tcp_port, tls_port, router
    finally:
        router.stop()


def test_hmi_jog_arrives_and_another_hosts_cmd_vel_never_does(acl_router) -> None:
    cert_dir, tcp_port, tls_port, router = acl_router
    received: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            received.append((str(sample.key_expr), sample.payload.to_bytes()))

    def seen(key: str, payload: bytes) -> bool:
        with lock:
            return (key, payload) in received

    sessions: list[zenoh.Session] = []
    try:
        robot = local_client(tcp_port)  # stands for drive: subscribes to cmd_vel and the pose database
        sessions.append(robot)
        robot.declare_subscriber("agv/r1/**", on_sample)
        robot.declare_subscriber(SENTINEL_KEY, on_sample)

        def on_goal(query: zenoh.Query) -> None:  # stands for nav: records the goal and accepts it
            with lock:
                received.append((str(query.key_expr), query.payload.to_bytes() if query.payload else b""))
            query.reply(query.key_expr, b"accepted")

        robot.declare_queryable("agv/r1/nav/goal", on_goal)
        hmi = tls_client(cert_dir, "zagv-hmi", tls_port)
        sessions.append(hmi)
        other = tls_client(cert_dir, "zagv-fleet", tls_port)  # same CA, another CN: a host that is not the HMI
        sessions.append(other)

        # the HMI's jog and pose edits are let through (republished until the router has routed them)
        def hmi_jog_arrived() -> bool:
            hmi.put("agv/r1/cmd_vel", b"hmi-jog")
            hmi.put("agv/r1/hmi/poses/dock", b"hmi-pose")
            return seen("agv/r1/cmd_vel", b"hmi-jog") and seen("agv/r1/hmi/poses/dock", b"hmi-pose")

        wait_for_sync(hmi_jog_arrived, timeout_s=20, poll_s=0.1,
                      message=f"the HMI's cmd_vel never arrived; router output:\n{router.output()}")

        # and so is its goal, which gets its reply
        def hmi_goal_answered() -> bool:
            replies = list(hmi.get("agv/r1/nav/goal", payload=b"hmi-goal", timeout=2.0))
            return any(r.ok is not None and r.ok.payload.to_bytes() == b"accepted" for r in replies)

        wait_for_sync(hmi_goal_answered, timeout_s=20, poll_s=0.1, message="the HMI's goal got no reply")
        assert seen("agv/r1/nav/goal", b"hmi-goal")

        # the other host's link is up and routed: its sentinel arrives
        def other_link_ready() -> bool:
            other.put(SENTINEL_KEY, b"before")
            return seen(SENTINEL_KEY, b"before")

        wait_for_sync(other_link_ready, timeout_s=20, poll_s=0.1,
                      message=f"the other host's sentinel never arrived; router output:\n{router.output()}")

        # denied puts and query, then a sentinel on the same session and priority: once it is in, they were dropped
        other.put("agv/r1/cmd_vel", b"other-jog")
        other.put("agv/r1/hmi/poses/dock", b"other-pose")
        other.get("agv/r1/nav/goal", payload=b"other-goal", timeout=2.0)  # replies, if any, are not awaited
        other.put(SENTINEL_KEY, b"after")
        wait_for_sync(lambda: seen(SENTINEL_KEY, b"after"), timeout_s=20,
                      message="the sentinel published after the denied puts never arrived")
        assert not seen("agv/r1/cmd_vel", b"other-jog"), "cmd_vel from a host that is not the HMI got through"
        assert not seen("agv/r1/hmi/poses/dock", b"other-pose"), "another host edited the pose database"
        assert not seen("agv/r1/nav/goal", b"other-goal"), "another host sent a goal"

        # both remote hosts may still observe the robot
        observed: list[str] = []
        other.declare_subscriber("agv/r1/odom", lambda s: observed.append(s.payload.to_bytes().decode()))

        def odom_observed() -> bool:
            robot.put("agv/r1/odom", b"odom")
            return bool(observed)

        wait_for_sync(odom_observed, timeout_s=20, poll_s=0.1, message="a remote host could not observe odom")
    finally:
        for session in sessions:
            session.close()


def test_a_certificate_from_another_ca_cannot_open_a_session(acl_router, tmp_path: Path) -> None:
    """Mutual TLS: the CN alone proves nothing; a zagv-hmi certificate signed by a foreign CA is turned away."""
    cert_dir, _tcp_port, tls_port, router = acl_router
    rogue_dir = tmp_path / "rogue"
    for args in (["ca"], ["zagv-hmi"]):
        subprocess.run(["sh", str(MAKE_CERTS), str(rogue_dir), *args], check=True, capture_output=True, timeout=60)
    conf = zenoh.Config.from_file(str(ZENOH_DIR / "client-hmi-tls.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{tls_port}"]))
    conf.insert_json5("connect/timeout_ms", "3000")
    conf.insert_json5("connect/exit_on_failure", "true")
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(cert_dir / "ca.pem")))
    conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(rogue_dir / "zagv-hmi.pem")))
    conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(rogue_dir / "zagv-hmi.key")))
    with pytest.raises(zenoh.ZError):
        zenoh.open(conf).close()
    assert router.running(), f"router died:\n{router.output()}"


#: (key after agv/r1/, message) the HMI host may send: each arrives
HMI_ALLOWED = [("nav/goal", "query"), ("nav/cancel", "query"), ("nav/waypoints", "query"),
               ("nav/waypoints/control", "query"), ("drive/estop", "query"), ("drive/disable", "query"),
               ("hmi/poses/dock", "query"), ("cmd_vel", "put"), ("hmi/poses/dock", "put")]
#: what deploy/README.md ("Access control", "Threat model") denies to the HMI host: each never arrives
HMI_DENIED = [("drive/enable", "query"), ("drive/release", "query"), ("localization/initial_pose", "query"),
              ("localization/save_map", "query"), ("localization/mode", "query"), ("localization/global", "query"),
              ("sim/teleport", "query"), ("odom", "put"), ("scan", "put"), ("map", "put"), ("drive/enable", "put"),
              ("localization/mode", "put"), ("nav/goal", "put"), ("cmd_vel", "delete")]
#: and to any other host: everything the HMI may send, and everything it may not
OTHER_DENIED = HMI_ALLOWED + HMI_DENIED


def test_every_deny_of_the_readme_holds_and_the_hmi_allows_pass(acl_router) -> None:
    cert_dir, tcp_port, tls_port, router = acl_router
    arrived: list[tuple[str, str, bytes]] = []
    lock = threading.Lock()

    def record(kind: str, key: str, payload: bytes) -> None:
        with lock:
            arrived.append((kind, key, payload))

    def seen(kind: str, key: str, payload: bytes) -> bool:
        with lock:
            return (kind, key, payload) in arrived

    sessions: list[zenoh.Session] = []
    try:
        robot = local_client(tcp_port)  # stands for every robot service: answers every query, hears every put
        sessions.append(robot)
        robot.declare_subscriber("agv/r1/**", lambda s: record(
            "put" if s.kind == zenoh.SampleKind.PUT else "delete", str(s.key_expr), s.payload.to_bytes()))
        robot.declare_subscriber(SENTINEL_KEY, lambda s: record("put", str(s.key_expr), s.payload.to_bytes()))
        keys = sorted({key for key, _ in OTHER_DENIED})

        def answer(query: zenoh.Query) -> None:
            record("query", str(query.key_expr), query.payload.to_bytes() if query.payload else b"")
            query.reply(query.key_expr, b"ok")

        for key in keys:
            robot.declare_queryable(f"agv/r1/{key}", answer)
        hmi = tls_client(cert_dir, "zagv-hmi", tls_port)
        other = tls_client(cert_dir, "zagv-fleet", tls_port)
        sessions += [hmi, other]

        def send(session: zenoh.Session, key: str, message: str, payload: bytes) -> None:
            if message == "put":
                session.put(f"agv/r1/{key}", payload)
            elif message == "delete":
                session.delete(f"agv/r1/{key}")
            else:
                session.get(f"agv/r1/{key}", payload=payload, timeout=2.0)

        for name, session in (("hmi", hmi), ("other", other)):
            def link_ready(session: zenoh.Session = session, name: str = name) -> bool:
                session.put(SENTINEL_KEY, f"{name}-ready".encode())
                return seen("put", SENTINEL_KEY, f"{name}-ready".encode())

            wait_for_sync(link_ready, timeout_s=20, poll_s=0.1,
                          message=f"{name}'s sentinel never arrived; router output:\n{router.output()}")

        # the HMI's allowed requests arrive (re-sent until the router has routed the robot's declarations)
        for key, message in HMI_ALLOWED:
            payload = f"hmi-{message}-{key}".encode()

            def allowed_arrived(key: str = key, message: str = message, payload: bytes = payload) -> bool:
                send(hmi, key, message, payload)
                return seen(message, f"agv/r1/{key}", payload)

            wait_for_sync(allowed_arrived, timeout_s=20, poll_s=0.1, message=f"the HMI's {message} {key} was dropped")

        # denied requests, then a sentinel on the same session: once it is in, the denied ones would have been too
        for name, session, denied in (("hmi", hmi, HMI_DENIED), ("other", other, OTHER_DENIED)):
            for key, message in denied:
                send(session, key, message, f"{name}-denied-{message}-{key}".encode())
            session.put(SENTINEL_KEY, f"{name}-after".encode())
            wait_for_sync(lambda name=name: seen("put", SENTINEL_KEY, f"{name}-after".encode()), timeout_s=20,
                          message=f"{name}'s sentinel after the denied requests never arrived")
            with lock:
                leaked = [(kind, key) for kind, key, payload in arrived
                          if payload.startswith(f"{name}-denied-".encode())]
                leaked += [(kind, key) for kind, key, _ in arrived if kind == "delete"]  # deletes carry no payload
            assert not leaked, f"denied to {name} but arrived: {leaked}"
    finally:
        for session in sessions:
            session.close()
