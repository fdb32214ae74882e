"""Scan stamps from the scanner's own clock (core, no I/O), as ROS drivers stamp with the device time.

The LMS1xx puts two U32 µs counters of its own clock in every ``LMDscandata``: the time of the first beam and the
time of transmission. Stamping a scan with its receive time minus the device delay (``receive - (tx - first)``)
gives every scan the jitter of its delivery, and a burst of telegrams read at once (a loaded host, or a simulated
clock that did not advance while they arrived) all the same stamp. Instead the device time is mapped onto the
service clock with one offset for the stream:

    stamp_k = first_k + median_{j in last N}(receive_j - tx_j)

with ``first`` and ``tx`` unwrapped to seconds. The median of the last ``window`` offsets follows the drift of the
device clock and ignores the late or stalled receive times of a burst, so stamps are unique and increase with the
device's own 1/f spacing. A candidate more than ``reset_s`` from the median (a device reboot, a restarted
simulator) starts a new estimate.
"""

from __future__ import annotations

import collections
import statistics

U32 = 2**32


class DeviceClockSync:
    """Maps the scanner's µs counters onto the service clock; one instance per connection (the device may reboot)."""

    def __init__(self, window: int = 250, reset_s: float = 5.0, max_delay_s: float = 0.5) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self.window = window
        self.reset_s = reset_s
        self.max_delay_s = max_delay_s
        self.offsets_s: collections.deque[float] = collections.deque(maxlen=window)
        self.resets = 0
        self._last_tx_us: int | None = None
        self._tx_s = 0.0  # unwrapped device time of transmission

    def stamp(self, receive_s: float, first_beam_us: int, transmission_us: int) -> float:
        """The first beam's time on the service clock (s), from its receive time and the two device counters."""
        if self._last_tx_us is not None:
            self._tx_s += ((transmission_us - self._last_tx_us) % U32) * 1e-6
        self._last_tx_us = transmission_us
        delay_s = ((transmission_us - first_beam_us) % U32) * 1e-6
        if delay_s > self.max_delay_s:  # implausible (a counter reset between the two): use the transmission time
            delay_s = 0.0
        offset_s = receive_s - self._tx_s
        if self.offsets_s and abs(offset_s - statistics.median(self.offsets_s)) > self.reset_s:
            self.offsets_s.clear()
            self.resets += 1
        self.offsets_s.append(offset_s)
        return self._tx_s - delay_s + statistics.median(self.offsets_s)
