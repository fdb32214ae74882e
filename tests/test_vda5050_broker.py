"""The vda5050 service on its own (``zagv up --vda5050 --only vda5050``, no robot) under npm ``vda-5050-lib``'s
MasterController, through the embedded amqtt broker (nothing installed; ``make test``) and through Debian's
mosquitto (``long``):
connection ONLINE with a state and a retained factsheet, 200 malformed inbound messages each answered by a
validationError in state, an unsupported instant action rejected, and a SIGKILL seen as CONNECTIONBROKEN (the MQTT
last will), then ONLINE and a state within 1 s after the restart. Every message the service publishes validates."""

from __future__ import annotations

import hashlib
import json
import os
import random
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.stack import Stack, free_port
from tests.support.vda5050 import MASTER_DIR, Master, Mosquitto, Recorder
from tests.support.waiting import wait_for_sync

pytestmark = [pytest.mark.integration]

BASE = "uagv/v2/zagv/r1"


class Rig:
    def __init__(self, stack: Stack, master: Master, recorder: Recorder) -> None:
        self.stack, self.master, self.recorder = stack, master, recorder


@pytest.fixture(params=["embedded", pytest.param("mosquitto", marks=pytest.mark.long)])
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Rig]:
    mosquitto = Mosquitto(tmp_path) if request.param == "mosquitto" else None
    if mosquitto is not None:
        port = mosquitto.port
        args = ["--vda5050", "--no-embedded-broker", "--set", f"vda5050.broker_port={port}"]
    else:
        port = free_port()
        args = ["--vda5050", "--mqtt-port", str(port)]
    stack = Stack(tmp_path, ["vda5050"], sim=False, extra_args=args)
    master = recorder = None
    try:
        stack.start(ready_timeout_s=60)
        stack.wait_line(r"vda5050: connected to MQTT broker", timeout_s=30)
        master = Master(port)
        recorder = Recorder(port, BASE)
        yield Rig(stack, master, recorder)
    finally:
        if master is not None:
            master.stop()
        if recorder is not None:
            recorder.stop()
        stack.stop()
        if mosquitto is not None:
            mosquitto.stop()


def _fuzzed(k: int, rnd: random.Random) -> tuple[str, bytes]:
    """Message ``k``: not JSON, the wrong JSON type, or a schema violation (unique through its index)."""
    header = {"headerId": 10_000 + k, "timestamp": "2026-01-01T00:00:00.00Z", "version": "2.0.0",
              "manufacturer": "zagv", "serialNumber": "r1"}
    topic = "order" if k % 2 else "instantActions"
    kind = (k // 2) % 8
    if kind == 0:
        return topic, bytes(rnd.getrandbits(8) for _ in range(rnd.randint(1, 64))) + f"#{k}".encode()
    if kind == 1:
        return topic, json.dumps([k, "not an object"]).encode()
    if kind == 2:
        return topic, json.dumps({**header, "timestamp": f"yesterday {k}"}).encode()
    if topic == "order":
        nodes = [{"nodeId": n, "sequenceId": 2 * i, "released": True, "actions": [],
                  "nodePosition": {"x": float(i), "y": 0.0, "mapId": "map"}} for i, n in enumerate("ab")]
        o = {"orderId": f"fuzz-{k}", "orderUpdateId": 0, "nodes": nodes,
             "edges": [{"edgeId": "ab", "sequenceId": 1, "released": True, "startNodeId": "a", "endNodeId": "b",
                        "actions": []}]}
        breakage = [lambda: o.pop("nodes"), lambda: o.update(orderUpdateId=-1),
                    lambda: nodes[0].update(released="yes"), lambda: o["edges"][0].pop("endNodeId"),
                    lambda: nodes[1]["nodePosition"].update(x="far")]
        breakage[kind - 3]()
        return topic, json.dumps({**header, **o}).encode()
    action = {"actionId": f"a{k}", "actionType": "startPause", "blockingType": "HARD"}
    breakage = [lambda: action.pop("actionId"), lambda: action.update(blockingType="SOMETIMES"),
                lambda: action.update(actionParameters=[{"key": "x"}]), lambda: action.update(actionType=7),
                lambda: action.update(actionId=None)]
    breakage[kind - 3]()
    return topic, json.dumps({**header, "instantActions": [action]}).encode()


def test_vda5050_service_under_a_third_party_master(rig: Rig) -> None:
    master, recorder, stack = rig.master, rig.recorder, rig.stack
    master.wait(lambda e: e["event"] == "connection" and e["state"] == "ONLINE", timeout_s=20, what="ONLINE")
    mark = master.send({"cmd": "instant", "actions": [{"actionId": "sr-0", "actionType": "stateRequest",
                                                       "blockingType": "NONE"}]})
    master.wait(lambda e: e["event"] == "actionState" and e["actionId"] == "sr-0" and e["actionStatus"] == "FINISHED",
                timeout_s=10, after=mark, what="stateRequest FINISHED")
    wait_for_sync(lambda: recorder.count("factsheet"), timeout_s=10, message="no retained factsheet")

    # 200 malformed messages: each is answered by a validationError naming its payload; the service keeps running
    pid = stack.pid("vda5050")
    rnd = random.Random(5050)
    unanswered = []
    started = time.monotonic()
    for first in range(0, 200, 10):  # in bursts of 10 (state keeps the last 20 message errors)
        mark = recorder.mark()
        burst = {}
        for k in range(first, first + 10):
            topic, payload = _fuzzed(k, rnd)
            burst[hashlib.sha256(payload).hexdigest()[:16]] = (k, topic, payload[:80])
            recorder.publish(topic, payload)

        def missing(mark: int = mark, burst: dict = burst) -> set[str]:
            seen = {r["referenceValue"] for s in recorder.states(mark) for e in s["errors"]
                    if e["errorType"] == "validationError" for r in e["errorReferences"]
                    if r["referenceKey"] == "payloadSha256"}
            return set(burst) - seen

        try:
            wait_for_sync(lambda missing=missing: not missing(), timeout_s=10)
        except AssertionError:
            unanswered += [burst[d] for d in missing()]
    print(f"200 malformed messages answered in {time.monotonic() - started:.1f} s")
    assert not unanswered, unanswered[:5]
    assert stack.pid("vda5050") == pid and os.path.exists(f"/proc/{pid}")

    # an unsupported instant action is rejected with an error in state, never ignored
    mark = master.send({"cmd": "instant", "actions": [{"actionId": "pick-1", "actionType": "pick",
                                                       "blockingType": "HARD"}]})
    event = master.wait(lambda e: e["event"] == "actionError" and e["actionId"] == "pick-1", timeout_s=10,
                        after=mark, what="the error for pick-1")
    assert event["error"]["errorType"] == "instantActionError"

    # SIGKILL: the broker delivers the last will; the supervisor restarts the service, which comes back ONLINE
    mark = master.mark()
    os.kill(pid, signal.SIGKILL)
    master.wait(lambda e: e["event"] == "connection" and e["state"] == "CONNECTIONBROKEN", timeout_s=15, after=mark,
                what="CONNECTIONBROKEN")
    online = master.wait(lambda e: e["event"] == "connection" and e["state"] == "ONLINE", timeout_s=60, after=mark,
                         what="ONLINE after the restart")
    state = master.wait(lambda e: e["event"] == "state" and e["t"] >= online["t"], timeout_s=5, after=mark,
                        what="a state after ONLINE")
    gap_s = (state["t"] - online["t"]) / 1000.0
    print(f"restart: first state {gap_s:.3f} s after ONLINE")
    assert gap_s <= 1.0
    assert stack.pid("vda5050") != pid

    # everything published validates: against the vendored official schemas and the master's own validators
    assert not recorder.invalid, recorder.invalid[:5]
    dropped = [line for line in master.stderr if "Drop inbound message" in line]
    assert not dropped, dropped[:5]


def test_master_dependency_is_pinned_with_a_lock() -> None:
    package = json.loads((MASTER_DIR / "package.json").read_text())
    lock = json.loads((MASTER_DIR / "package-lock.json").read_text())
    assert package["dependencies"]["vda-5050-lib"] == "1.4.0"
    assert lock["packages"]["node_modules/vda-5050-lib"]["version"] == "1.4.0"
