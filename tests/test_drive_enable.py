"""The drive's enable and e-stop policy (services/drive/enable.py): refusals and answers, without a bus."""

from __future__ import annotations

from services.drive.enable import enable_refusal, estop_sent, estop_unreachable, release_refusal, release_sent


def test_enable_needs_no_estop_and_a_link() -> None:
    refused = enable_refusal(estopped=True, link_ok=True, link_fault="")
    assert refused is not None and not refused.ok and "release it first" in refused.message
    down = enable_refusal(estopped=False, link_ok=False, link_fault="no heartbeat from node 2")
    assert down is not None and not down.ok and "no heartbeat from node 2" in down.message
    assert enable_refusal(estopped=False, link_ok=True, link_fault="") is None


def test_estop_is_latched_whether_or_not_the_controllers_answer() -> None:
    later = estop_unreachable(False, "bus off")
    assert later is not None and later.ok and "bus off" in later.message and "when the link returns" in later.message
    assert estop_unreachable(True, "") is None
    assert estop_sent([]).ok and "every controller" in estop_sent([]).message
    partial = estop_sent(["node 2: SDO timeout"])
    assert partial.ok and "node 2: SDO timeout" in partial.message


def test_release_needs_an_estop_a_link_and_every_controller() -> None:
    nothing = release_refusal(estopped=False, link_ok=False, link_fault="x")
    assert nothing is not None and nothing.ok and nothing.message == "no e-stop active"
    down = release_refusal(estopped=True, link_ok=False, link_fault="bus off")
    assert down is not None and not down.ok and "bus off" in down.message
    assert release_refusal(estopped=True, link_ok=True, link_fault="") is None
    assert release_sent([]).ok
    failed = release_sent(["node 1: refused"])
    assert not failed.ok and "node 1: refused" in failed.message
