"""Composition: several services in one process (services/launch/container.py, ``zagv up --compose``)."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import threading
from types import SimpleNamespace
from typing import cast

import pytest

from proto import Keys, encode
from proto.messages import Odometry, Twist2D
from services.client.status import collect
from services.common.config import ConfigError
from services.common.node import SUBSCRIBER_QUEUE, Node, SharedReader
from services.common.service import PreparedService
from services.common.session import open_session
from services.common.settings import ZenohSettings
from services.launch.container import Container, parse_shared_loops, split_groups
from services.launch.up import DEFAULT_COMPOSITION, StackPlan, compose_from_args, parse_compose, plan_from_args
from tests.support.waiting import wait_for


def test_groups_are_split_on_the_separator_and_checked():
    assert split_groups(["nav", "--robot-id", "r2", "::", "localization"]) == [
        ("nav", ["--robot-id", "r2"]), ("localization", [])]
    with pytest.raises(ConfigError, match="'sim' cannot run in a container"):
        split_groups(["sim"])
    with pytest.raises(ConfigError, match="nav is given twice"):
        split_groups(["nav", "::", "nav"])
    with pytest.raises(ConfigError, match="empty service"):
        split_groups(["nav", "::"])


def test_shared_loops_name_services_of_the_container_once():
    names = ["lidar", "safety", "nav", "localization"]
    assert parse_shared_loops(["nav, localization", "lidar,safety"], names) == [["nav", "localization"],
                                                                               ["lidar", "safety"]]
    with pytest.raises(ConfigError, match="'recorder' is not a service of this container"):
        parse_shared_loops(["nav,recorder"], names)
    with pytest.raises(ConfigError, match="nav is given twice"):
        parse_shared_loops(["nav,localization", "nav,lidar"], names)
    with pytest.raises(ConfigError, match="names no service"):
        parse_shared_loops([" , "], names)


def test_a_shared_loop_runs_where_its_first_service_was_and_the_others_keep_loops_of_their_own():
    services = [cast(PreparedService, SimpleNamespace(name=n)) for n in ["lidar", "safety", "localization", "nav",
                                                                         "recorder", "hmi_api"]]
    groups = Container(services, [["nav", "localization", "recorder"], ["hmi_api", "lidar"]]).loop_groups()
    assert [[p.name for p in g] for g in groups] == [["lidar", "hmi_api"], ["safety"],
                                                     ["localization", "nav", "recorder"]]
    assert [[p.name for p in g] for g in Container(services).loop_groups()] == [[n.name] for n in services]


def test_a_container_refuses_a_shared_loop_naming_a_service_it_does_not_run():
    result = subprocess.run([sys.executable, "-m", "services.launch.container", "--name", "c", "--shared-loop",
                             "nav,bogus", "nav", "::", "localization"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "--shared-loop: 'bogus' is not a service of this container (nav, localization)" in result.stderr


def test_zagv_up_runs_each_group_as_one_child_and_keeps_the_drive_apart():
    assert "drive" not in DEFAULT_COMPOSITION and "sim" not in DEFAULT_COMPOSITION
    plan = StackPlan(sim=True, compose=parse_compose(["default"]), run_dir="/nonexistent")
    names = [c.name for c in plan.children()]
    assert names == ["canbus", "sim", "drive", "components"]
    argv = plan.children()[-1].argv
    members = [argv[i + 1] for i, a in enumerate(argv) if a == "::"]
    assert argv[argv.index("--name"):argv.index("--name") + 7] == [
        "--name", "components", "--shared-loop", "lidar,safety", "--shared-loop", "localization,nav,recorder,hmi_api",
        "lidar"]
    assert members == ["safety", "localization", "nav", "recorder", "hmi_api"]
    isolated = StackPlan(sim=True, compose=parse_compose(["default"]), run_dir="/x", shared_loop=False)
    assert "--shared-loop" not in isolated.children()[-1].argv
    two = StackPlan(sim=False, compose=parse_compose(["lidar,safety", "nav,localization"]), run_dir="/x")
    assert [c.name for c in two.children()] == ["drive", "components", "components-2", "recorder", "hmi_api"]
    one_left = StackPlan(sim=False, only=["drive", "nav"], compose=parse_compose(["nav,localization"]), run_dir="/x")
    assert [c.name for c in one_left.children()] == ["drive", "nav"]  # a group of one runs on its own
    with pytest.raises(ValueError, match="'sim' cannot run in a container"):
        parse_compose(["sim,nav"])
    with pytest.raises(ValueError, match="nav is in two groups"):
        parse_compose(["nav,lidar", "nav"])


def test_zagv_up_composes_by_default_and_runs_each_service_alone_with_no_compose(tmp_path):
    from services.cli.main import build_parser

    def plan(*argv: str) -> StackPlan:
        args = build_parser().parse_args(["up", "--sim", "--run-dir", "/tmp/zagv-test-unused", *argv])
        return StackPlan(sim=True, compose=compose_from_args(args), run_dir="/x")

    assert [c.name for c in plan().children()] == ["canbus", "sim", "drive", "components"]
    parser = build_parser()
    shared = plan_from_args(parser.parse_args(["up", "--sim", "--run-dir", str(tmp_path)]))
    isolated = plan_from_args(parser.parse_args(["up", "--sim", "--run-dir", str(tmp_path), "--isolated-loops"]))
    assert shared.children()[-1].argv.count("--shared-loop") == 2
    assert "--shared-loop" not in isolated.children()[-1].argv
    assert [c.name for c in plan("--no-compose").children()] == [
        "canbus", "sim", "drive", "lidar", "safety", "localization", "nav", "recorder", "hmi_api"]
    assert [c.name for c in plan("--compose", "nav,localization").children()] == [
        "canbus", "sim", "drive", "lidar", "safety", "components", "recorder", "hmi_api"]
    with pytest.raises(ValueError, match="--compose and --no-compose together"):
        plan("--compose", "--no-compose")


@pytest.fixture
def session(router):
    s = open_session(ZenohSettings(connect=[router]))
    yield s
    s.close()


async def test_nodes_of_one_process_share_a_reader_per_key(session, router):
    keys = Keys("c1")
    a, b = Node("a", session, keys), Node("b", session, keys)
    got_a: list[float] = []
    got_b: list[float] = []
    a.subscribe("cmd_vel", lambda m: got_a.append(m.vx))
    b.subscribe("cmd_vel", lambda m: got_b.append(m.vx))
    shared = [r for k, r in SharedReader._registry.items() if k[1] == keys("cmd_vel") and r.session is session]
    assert len(shared) == 1 and len(shared[0].listeners) == 2
    publisher = open_session(ZenohSettings(connect=[router]))
    try:
        pub = publisher.declare_publisher(keys("cmd_vel"))
        await wait_for(lambda: (pub.put(encode(Twist2D(vx=0.5))), bool(got_a) and bool(got_b))[1], timeout_s=5)
        a.close()  # b keeps the reader
        assert len(shared[0].listeners) == 1
        n = len(got_b)
        await wait_for(lambda: (pub.put(encode(Twist2D(vx=0.7))), len(got_b) > n)[1], timeout_s=5)
        b.close()  # the last one out undeclares it
        assert shared[0].registry_key not in SharedReader._registry
    finally:
        publisher.close()


async def test_a_newest_only_listener_and_a_deeper_one_share_the_deeper_ring(session, router):
    """hmi_api asks for depth 1 (newest only) where safety and nav ask for the default ring: one reader serves all,
    re-declared deeper when the deeper listener comes second; a keep-every-message FIFO stays a reader of its own."""
    keys = Keys("c3")
    newest, ring, fifo = Node("newest", session, keys), Node("ring", session, keys), Node("fifo", session, keys)
    got: dict[str, list[float]] = {"newest": [], "ring": [], "fifo": [], "raw": []}
    newest.subscribe("odom", lambda m: got["newest"].append(m.stamp), queue=1, on_zenoh_thread=True)

    def readers() -> list[SharedReader]:
        return [r for k, r in SharedReader._registry.items() if k[1] == keys("odom") and r.session is session]

    assert [r.queue for r in readers()] == [1]
    ring.subscribe("odom", lambda m: got["ring"].append(m.stamp))
    ring.subscribe_raw("odom", lambda s: got["raw"].append(1.0))
    assert [(r.queue, len(r.listeners)) for r in readers()] == [(SUBSCRIBER_QUEUE, 3)]  # re-declared deeper
    fifo.subscribe("odom", lambda m: got["fifo"].append(m.stamp), queue=None)
    assert sorted((r.queue or 0, len(r.listeners)) for r in readers()) == [(0, 1), (SUBSCRIBER_QUEUE, 3)]
    publisher = open_session(ZenohSettings(connect=[router]))
    try:
        pub = publisher.declare_publisher(keys("odom"))
        stamp = iter(range(1, 10_000))

        def every_listener_got_one() -> bool:
            pub.put(encode(Odometry(stamp=float(next(stamp)))))
            return all(got.values())

        await wait_for(every_listener_got_one, timeout_s=5)
        newest.close()  # joined the shallow reader, leaves the deep one that replaced it
        assert sorted(len(r.listeners) for r in readers()) == [1, 2]
        ring.close()
        fifo.close()
        assert readers() == []
    finally:
        publisher.close()


async def test_messages_that_arrive_together_share_one_loop_wake_up(session):
    node = Node("n", session, Keys("c2"))
    delivered: list[int] = []
    release = threading.Event()

    def post_three() -> None:
        for i in range(3):
            node._post(delivered.append, i)
        release.set()

    # the loop is held in this coroutine while another thread posts three messages: one drain takes all three
    thread = threading.Thread(target=post_three)
    thread.start()
    release.wait(5.0)
    thread.join()
    assert node.loop_wakeups == 1 and delivered == []
    await asyncio.sleep(0)
    assert delivered == [0, 1, 2]
    node._post(delivered.append, 3)  # the next one schedules a new drain
    await asyncio.sleep(0)
    assert delivered == [0, 1, 2, 3] and node.loop_wakeups == 2
    node.close()


@pytest.mark.integration
def test_a_composed_stack_reaches_a_goal_answers_for_every_service_and_restarts_as_one(stack_factory):
    stack = stack_factory(None, speed=2.0, extra_args=["--compose"])
    stack.start(ready_timeout_s=120)
    composed = ["lidar", "safety", "localization", "nav", "recorder", "hmi_api"]
    stack.wait_line(r"running lidar, safety, localization, nav, recorder, hmi_api in one process "
                    r"\(lidar, safety on one event loop\) \(localization, nav, recorder, hmi_api on one event loop\)",
                    timeout_s=30)
    assert stack.pid("drive") != stack.pid("components")
    assert {stack.pid(s) for s in composed} == {stack.pid("components")}
    # every composed service answers a wildcard query (each replies on its own key: none is consolidated away)
    report = collect(stack.session(), stack.robot_id, 3.0)
    assert all(report[s]["healthy"] and report[s]["stats"].get("service") == s for s in [*composed, "drive"]), report

    goal = subprocess.run([sys.executable, "-m", "services.cli", "goal", "3.0", "0.1", "1.57", "--timeout", "300",
                           "--connect", stack.endpoint, "--robot-id", stack.robot_id],
                          capture_output=True, text=True, timeout=600)
    assert goal.returncode == 0 and "succeeded" in goal.stdout, goal.stdout + goal.stderr

    # a kill takes the whole container; the supervisor restarts it and every service's token comes back
    mark = stack.line_count()
    old_pid = stack.pid("components")
    os.kill(old_pid, signal.SIGKILL)
    for service in composed:
        stack.wait_line(rf"^zagv: {service} healthy again", timeout_s=120, after=mark)
    assert stack.pid("components") != old_pid
