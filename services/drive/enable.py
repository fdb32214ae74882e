"""The drive's enable and e-stop policy, as plain decisions on the loop's state (no I/O).

- ``drive/enable`` is refused while an e-stop is latched (release it first) or while the CAN link is down;
  otherwise the controller's ramps are reset and the drive is enabled.
- ``drive/disable`` always succeeds: the wheels are commanded to stop.
- ``drive/estop`` latches at once (the next cycle commands zero, whatever the controllers answer), then sends
  ``!EX`` to every controller; with the link down ``!EX`` goes out when the link returns.
- ``drive/release`` needs the link (``!MG`` on every controller); without a latched e-stop there is nothing to do.
"""

from __future__ import annotations

from proto.messages import Reply


def enable_refusal(estopped: bool, link_ok: bool, link_fault: str) -> Reply | None:
    """Why ``drive/enable`` is refused, or None when the drive may be enabled."""
    if estopped:
        return Reply(ok=False, message="e-stop active: release it first (drive/release)")
    if not link_ok:
        return Reply(ok=False, message=f"CAN link down: {link_fault}")
    return None


ENABLED = Reply(ok=True, message="drive enabled")
DISABLED = Reply(ok=True, message="drive disabled: wheels stopped")


def estop_unreachable(link_ok: bool, link_fault: str) -> Reply | None:
    """The e-stop answer when the controllers cannot be told now (None: send ``!EX``)."""
    if link_ok:
        return None
    return Reply(ok=True, message=f"e-stop latched in drive; controllers unreachable ({link_fault}), "
                                  "!EX is sent when the link returns")


def estop_sent(failures: list[str]) -> Reply:
    """The e-stop answer after ``!EX``: latched either way; the controllers that did not take it are named."""
    if failures:
        return Reply(ok=True, message="e-stop latched in drive; !EX failed on: " + "; ".join(failures))
    return Reply(ok=True, message="e-stop active on every controller (!EX)")


def release_refusal(estopped: bool, link_ok: bool, link_fault: str) -> Reply | None:
    """The release answer when ``!MG`` is not sent (no e-stop, or no link); None: send it."""
    if not estopped:
        return Reply(ok=True, message="no e-stop active")
    if not link_ok:
        return Reply(ok=False, message=f"CAN link down, cannot release the controllers: {link_fault}")
    return None


def release_sent(failures: list[str]) -> Reply:
    """The release answer after ``!MG``: released only when every controller took it."""
    if failures:
        return Reply(ok=False, message="!MG failed on: " + "; ".join(failures))
    return Reply(ok=True, message="e-stop released (!MG)")
