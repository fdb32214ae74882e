"""The site topology of deploy/site.md on loopback: a robot's router dials the site router over mutual TLS, and the
two access controls keep the site to observing and to the fleet view's queries.

Real ``zagv router`` processes run ``deploy/zenoh/site-router-tls.json5`` and, for each robot,
``deploy/zenoh/router-lan-tls.json5`` with only endpoints and certificate paths replaced (certificates from
``deploy/zenoh/make-certs.sh``). A peer on the robot router's loopback port stands for the robot's services: it
answers every query and hears every put. A client on the site router's loopback port stands for the fleet view.
"Never arrives" is shown by ordering: after the denied requests the site client sends a sentinel on the same
session and priority, which both routers forward in order, so once it is in, the denied ones would have been too.
With the site router's access control switched off (a site router misconfigured or taken over), the robot's own
router still refuses everything but the fleet view's queries.
"""

from __future__ import annotations

import json
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
from tests.test_deploy_zenoh_acl import MAKE_CERTS, ZENOH_DIR, make_certs

pytestmark = pytest.mark.integration
SENTINEL_KEY = "zagv-test/sentinel"

#: (key after agv/r1/, message) the site may send: each arrives at the robot's services
SITE_ALLOWED = [("nav/goal", "query"), ("nav/cancel", "query"), ("nav/waypoints", "query"),
                ("nav/waypoints/control", "query"), ("drive/estop", "query"), ("drive/disable", "query")]
#: what deploy/site.md denies to the site: each never arrives
SITE_DENIED = [("drive/enable", "query"), ("drive/release", "query"), ("localization/initial_pose", "query"),
               ("localization/mode", "query"), ("sim/teleport", "query"), ("hmi/poses/dock", "query"),
               ("cmd_vel", "put"), ("safety/cmd_vel", "put"), ("hmi/poses/dock", "put"), ("odom", "put"),
               ("map", "put"), ("cmd_vel", "delete")]


def sentinel_rule(policy_subjects: list[str]) -> tuple[dict, dict]:
    """A test-only rule and policy letting the sentinel through, on a key no deployed rule mentions."""
    rule = {"id": "test-sentinel", "permission": "allow", "flows": ["ingress", "egress"],
            "messages": ["put", "declare_subscriber"], "key_exprs": [SENTINEL_KEY]}
    return rule, {"id": "test-sentinel", "rules": ["test-sentinel"], "subjects": policy_subjects}


def site_config(cert_dir: Path, tcp_port: int, tls_port: int, acl: bool) -> dict:
    conf = json.loads(str(zenoh.Config.from_file(str(ZENOH_DIR / "site-router-tls.json5"))))
    conf["listen"]["endpoints"] = [f"tcp/127.0.0.1:{tcp_port}", f"tls/127.0.0.1:{tls_port}"]
    tls = conf["transport"]["link"]["tls"]
    tls.update(root_ca_certificate=str(cert_dir / "ca.pem"), listen_certificate=str(cert_dir / "zagv-site.pem"),
               listen_private_key=str(cert_dir / "zagv-site.key"))
    rule, policy = sentinel_rule(["robots"])
    conf["access_control"]["rules"].append(rule)
    conf["access_control"]["policies"].append(policy)
    conf["access_control"]["enabled"] = acl
    return conf


def robot_config(cert_dir: Path, name: str, tcp_port: int, tls_port: int, site_tls_port: int) -> dict:
    conf = json.loads(str(zenoh.Config.from_file(str(ZENOH_DIR / "router-lan-tls.json5"))))
    conf["listen"]["endpoints"] = [f"tcp/127.0.0.1:{tcp_port}", f"tls/127.0.0.1:{tls_port}"]
    conf["connect"]["endpoints"] = [f"tls/localhost:{site_tls_port}"]
    tls = conf["transport"]["link"]["tls"]
    tls.update(root_ca_certificate=str(cert_dir / "ca.pem"),
               listen_certificate=str(cert_dir / f"{name}.pem"), listen_private_key=str(cert_dir / f"{name}.key"),
               connect_certificate=str(cert_dir / f"{name}.pem"), connect_private_key=str(cert_dir / f"{name}.key"))
    rule, policy = sentinel_rule(["site"])
    conf["access_control"]["rules"].append(rule)
    conf["access_control"]["policies"].append(policy)
    return conf


def start_router(path: Path, conf: dict) -> RouterProcess:
    path.write_text(json.dumps(conf, indent=1))
    router = RouterProcess(["--config", str(path)]).start()
    wait_for_sync(lambda: any("listening on" in line for line in router.lines) or not router.running(),
                  timeout_s=30, message=f"router {path.name} did not start")
    assert router.running(), f"router {path.name} exited:\n{router.output()}"
    return router


def tls_observer(cert_dir: Path, name: str, tls_port: int) -> zenoh.Session:
    conf = zenoh.Config.from_file(str(ZENOH_DIR / "client-hmi-tls.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{tls_port}"]))
    conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(cert_dir / "ca.pem")))
    conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(cert_dir / f"{name}.pem")))
    conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(cert_dir / f"{name}.key")))
    return zenoh.open(conf)


@pytest.fixture(scope="module")
def site_certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cert_dir = tmp_path_factory.mktemp("site") / "tls"
    make_certs(cert_dir)  # ca, zagv-router, zagv-hmi, zagv-fleet (and skips without openssl)
    for args in (["zagv-site", "DNS:localhost", "IP:127.0.0.1"], ["zagv-router-r1", "DNS:localhost"],
                 ["zagv-router-r9", "DNS:localhost"], ["zagv-observer"]):
        subprocess.run(["sh", str(MAKE_CERTS), str(cert_dir), *args], check=True, capture_output=True, timeout=60)
    return cert_dir


class Recorder:
    """What the robot's services (and the sentinel's subscriber) received: (kind, key, payload)."""

    def __init__(self) -> None:
        self.items: list[tuple[str, str, bytes]] = []
        self.lock = threading.Lock()

    def add(self, kind: str, key: str, payload: bytes) -> None:
        with self.lock:
            self.items.append((kind, key, payload))

    def seen(self, kind: str, key: str, payload: bytes) -> bool:
        with self.lock:
            return (kind, key, payload) in self.items

    def leaked(self, prefix: bytes) -> list[tuple[str, str]]:
        with self.lock:
            return [(k, key) for k, key, p in self.items if p.startswith(prefix) or k == "delete"]


@pytest.fixture(scope="module", params=[True, False], ids=["both-acls", "robot-acl-alone"])
def site(request: pytest.FixtureRequest, site_certs: Path, tmp_path_factory: pytest.TempPathFactory
         ) -> Iterator[dict]:
    """The site router (its access control on or off) and the routers of robots r1 and r9, for the module."""
    tmp_path = tmp_path_factory.mktemp("routers")
    ports = {name: free_port() for name in ("site_tcp", "site_tls", "r1_tcp", "r1_tls", "r9_tcp", "r9_tls")}
    routers = [start_router(tmp_path / "site.json5", site_config(site_certs, ports["site_tcp"], ports["site_tls"],
                                                                 acl=request.param))]
    try:
        for rid in ("r1", "r9"):
            routers.append(start_router(tmp_path / f"{rid}.json5", robot_config(
                site_certs, f"zagv-router-{rid}", ports[f"{rid}_tcp"], ports[f"{rid}_tls"], ports["site_tls"])))
        yield {"certs": site_certs, "ports": ports, "routers": routers, "site_acl": request.param}
    finally:
        for router in routers:
            router.stop()


def test_the_site_observes_and_sends_only_the_fleet_views_queries(site: dict) -> None:
    ports, routers = site["ports"], site["routers"]
    got = Recorder()
    sessions: list[zenoh.Session] = []
    try:
        robot = open_session(ZenohSettings(mode="peer", connect=[f"tcp/127.0.0.1:{ports['r1_tcp']}"]))
        sessions.append(robot)
        robot.declare_subscriber("agv/r1/**", lambda s: got.add(
            "put" if s.kind == zenoh.SampleKind.PUT else "delete", str(s.key_expr), s.payload.to_bytes()))
        robot.declare_subscriber(SENTINEL_KEY, lambda s: got.add("put", SENTINEL_KEY, s.payload.to_bytes()))

        def answer(query: zenoh.Query) -> None:
            got.add("query", str(query.key_expr), query.payload.to_bytes() if query.payload else b"")
            query.reply(query.key_expr, b"ok")

        for key in sorted({k for k, _ in SITE_ALLOWED + SITE_DENIED}):
            robot.declare_queryable(f"agv/r1/{key}", answer)
        token = robot.liveliness().declare_token("agv/r1/@health/nav")
        fleet = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{ports['site_tcp']}"]))
        sessions.append(fleet)

        # the site sees the robot: its health token and its data
        present: list[str] = []
        fleet.liveliness().declare_subscriber("agv/*/@health/*", lambda s: present.append(str(s.key_expr)),
                                              history=True)
        odom: list[str] = []
        fleet.declare_subscriber("agv/*/odom", lambda s: odom.append(str(s.key_expr)))

        def robot_observed() -> bool:
            robot.put("agv/r1/odom", b"odom")
            return "agv/r1/@health/nav" in present and "agv/r1/odom" in odom

        wait_for_sync(robot_observed, timeout_s=30, poll_s=0.1, message="the site never saw robot r1:\n"
                      + "\n".join(r.output() for r in routers))

        def link_ready() -> bool:
            fleet.put(SENTINEL_KEY, b"ready")
            return got.seen("put", SENTINEL_KEY, b"ready")

        wait_for_sync(link_ready, timeout_s=20, poll_s=0.1, message="the sentinel never reached the robot")

        for key, message in SITE_ALLOWED:
            payload = f"site-{message}-{key}".encode()

            def allowed_arrived(key: str = key, payload: bytes = payload) -> bool:
                fleet.get(f"agv/r1/{key}", payload=payload, timeout=2.0)
                return got.seen("query", f"agv/r1/{key}", payload)

            wait_for_sync(allowed_arrived, timeout_s=20, poll_s=0.1, message=f"the site's {message} {key} was dropped")

        for key, message in SITE_DENIED:
            payload = f"denied-{message}-{key}".encode()
            if message == "put":
                fleet.put(f"agv/r1/{key}", payload)
            elif message == "delete":
                fleet.delete(f"agv/r1/{key}")
            else:
                fleet.get(f"agv/r1/{key}", payload=payload, timeout=2.0)
        fleet.put(SENTINEL_KEY, b"after")
        wait_for_sync(lambda: got.seen("put", SENTINEL_KEY, b"after"), timeout_s=20,
                      message="the sentinel after the denied requests never arrived")
        assert not got.leaked(b"denied-"), f"denied to the site but arrived: {got.leaked(b'denied-')}"
        token.undeclare()
        wait_for_sync(lambda: present.count("agv/r1/@health/nav") >= 2, timeout_s=20,
                      message="the site never saw the robot's health token go")
    finally:
        for s in sessions:
            s.close()


def test_an_unlisted_robot_and_a_stranger_see_nothing_an_observer_only_watches(site: dict) -> None:
    if not site["site_acl"]:
        pytest.skip("about the site router's own access control")
    certs, ports = site["certs"], site["ports"]
    sessions: list[zenoh.Session] = []
    try:
        r1 = open_session(ZenohSettings(mode="peer", connect=[f"tcp/127.0.0.1:{ports['r1_tcp']}"]))
        r9 = open_session(ZenohSettings(mode="peer", connect=[f"tcp/127.0.0.1:{ports['r9_tcp']}"]))
        fleet = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{ports['site_tcp']}"]))
        observer = tls_observer(certs, "zagv-observer", ports["site_tls"])
        stranger = tls_observer(certs, "zagv-fleet", ports["site_tls"])  # a CA certificate no subject lists
        sessions += [r1, r9, fleet, observer, stranger]
        heard: dict[str, list[str]] = {"fleet": [], "observer": [], "stranger": []}
        for name, session in (("fleet", fleet), ("observer", observer), ("stranger", stranger)):
            session.declare_subscriber("agv/*/odom", lambda s, name=name: heard[name].append(str(s.key_expr)))
        queried: list[str] = []
        r1.declare_queryable("agv/r1/nav/goal", lambda q: (queried.append("observer"), q.reply(q.key_expr, b"ok")))

        def r1_heard_often() -> bool:
            r1.put("agv/r1/odom", b"odom")
            r9.put("agv/r9/odom", b"odom")
            return heard["fleet"].count("agv/r1/odom") >= 20 and heard["observer"].count("agv/r1/odom") >= 20

        wait_for_sync(r1_heard_often, timeout_s=30, poll_s=0.05, message=f"r1's odom did not reach the site: {heard}")
        assert "agv/r9/odom" not in heard["fleet"] + heard["observer"], "a robot the site does not list got in"
        assert not heard["stranger"], "a certificate no subject lists observed the robots"
        replies = list(observer.get("agv/r1/nav/goal", payload=b"observer-goal", timeout=2.0))
        assert not any(r.ok is not None for r in replies) and not queried, "an observer sent a goal"
    finally:
        for s in sessions:
            s.close()
