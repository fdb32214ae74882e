"""Scan stamps from the scanner's own clock (core, no I/O), as ROS drivers stamp with the device time.

The LMS1xx puts two U32 µs counters of its own clock in every ``LMDscandata``: the time of the first beam and the
time of transmission. Stamping a scan with its receive time minus the device delay (``receive - (tx - first)``)
gives every scan the jitter of its delivery, and a burst of telegrams read at once (a loaded host, or a simulated
clock that did not advance while they arrived) all the same stamp. Instead the device time is mapped onto the
service clock with one offset for the stream, the lower envelope of the observed offsets:

    stamp_k = first_k + quantile_q{receive_j - tx_j : j among the last N}    (q = 5 %: the lower envelope)

with ``first`` and ``tx`` unwrapped to seconds. Every observed offset is the true one plus that telegram's delivery
delay (network, host scheduling, a loaded event loop), which is never negative: the smallest of them is the closest
to the truth (the passive synchronisation of Olson 2010, the lower envelope ROS drivers' time filters track). A low
quantile rather than the minimum keeps one telegram whose receive time ran behind its transmission (a simulated clock
read late, a host clock stepped back) from pulling every stamp early. A median would put the typical delivery delay
into every stamp: under load, scans delivered 0.5 s late would be stamped 0.5 s late and placed with the odometry of
a pose the robot had already moved past. The window of ``window`` telegrams follows the drift of the device clock;
the estimate rises by at most ``max_drift`` s per s of device time (a quartz drifts by 10-100 ppm), so that a spell
of load longer than the window neither stamps its scans late nor, when it ends, sends the stamps back in time.
A telegram received at the very same service-clock time as the one before came while that clock stood still (a
simulated clock not advanced while telegrams arrived; a wall clock reads differently on every read, also in a
burst): its receive time says nothing about when it was sent, and it is left out of the estimate. A candidate more
than ``reset_s`` from the estimate (a device reboot, a restarted simulator) starts a new estimate.
"""

from __future__ import annotations

import bisect
import collections

U32 = 2**32


class DeviceClockSync:
    """Maps the scanner's µs counters onto the service clock; one instance per connection (the device may reboot)."""

    def __init__(self, window: int = 250, reset_s: float = 5.0, max_delay_s: float = 0.5,
                 quantile: float = 0.05, max_drift: float = 2e-4) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if not 0.0 <= quantile <= 0.5:
            raise ValueError(f"quantile must be within [0, 0.5], got {quantile}")
        if max_drift < 0.0:
            raise ValueError(f"max_drift must be >= 0, got {max_drift}")
        self.quantile = quantile
        self.max_drift = max_drift
        self._estimate_s: float | None = None
        self.window = window
        self.reset_s = reset_s
        self.max_delay_s = max_delay_s
        #: offsets (s) of the telegrams among the last ``window`` received while the service clock moved, with their
        #: telegram index
        self.offsets_s: collections.deque[tuple[int, float]] = collections.deque()
        #: the same offsets in ascending order, kept with bisection as telegrams come and go (the quantile is then
        #: read off, instead of sorting the window for every telegram)
        self._ordered_s: list[float] = []
        self.resets = 0
        #: telegrams left out of the estimate (received while the service clock stood still)
        self.stalled = 0
        self._count = 0
        self._last_tx_us: int | None = None
        self._last_receive_s: float | None = None
        self._tx_s = 0.0  # unwrapped device time of transmission

    @property
    def offset_s(self) -> float | None:
        """The current estimate of service clock minus device clock (s); None before the first telegram."""
        return self._estimate_s

    def _window_quantile(self) -> float | None:
        ordered = self._ordered_s
        if not ordered:
            return None
        return ordered[int(self.quantile * (len(ordered) - 1))]

    def stamp(self, receive_s: float, first_beam_us: int, transmission_us: int) -> float:
        """The first beam's time on the service clock (s), from its receive time and the two device counters."""
        tx_step_s = 0.0
        if self._last_tx_us is not None:
            tx_step_s = ((transmission_us - self._last_tx_us) % U32) * 1e-6
            self._tx_s += tx_step_s
        self._last_tx_us = transmission_us
        delay_s = ((transmission_us - first_beam_us) % U32) * 1e-6
        if delay_s > self.max_delay_s:  # implausible (a counter reset between the two): use the transmission time
            delay_s = 0.0
        offset_s = receive_s - self._tx_s
        current = self.offset_s
        if current is not None and abs(offset_s - current) > self.reset_s:
            self.offsets_s.clear()
            self._ordered_s.clear()
            self.resets += 1
            current = self._estimate_s = None
        moved = current is None or self._last_receive_s is None or receive_s > self._last_receive_s
        self._last_receive_s = receive_s
        self._count += 1
        while self.offsets_s and self.offsets_s[0][0] <= self._count - self.window:
            _, old_s = self.offsets_s.popleft()
            del self._ordered_s[bisect.bisect_left(self._ordered_s, old_s)]
        if moved:
            self.offsets_s.append((self._count, offset_s))
            bisect.insort(self._ordered_s, offset_s)
        else:
            self.stalled += 1
        estimate = self._window_quantile()
        if estimate is None:  # the clock stood still for the whole window: this offset is all there is
            estimate = offset_s
        if current is not None:
            estimate = min(estimate, current + self.max_drift * tx_step_s)
        self._estimate_s = estimate
        return self._tx_s - delay_s + estimate
