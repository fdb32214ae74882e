"""Ports chosen for another process stay out of the kernel's ephemeral range, where a port-0 bind could take them."""

from __future__ import annotations

import random
import socket

from services.common import ports


def test_chosen_ports_are_free_and_outside_the_ephemeral_range():
    low, high = ports.ephemeral_range()
    chosen = [ports.free_port(random.Random(seed)) for seed in range(50)]
    assert all(not (low <= p <= high) and p >= ports.LOWEST_CHOSEN_PORT for p in chosen), (low, high, chosen)
    assert all(ports.bindable(p) for p in chosen)


def test_a_port_in_use_is_never_chosen(monkeypatch):
    with socket.socket() as held:
        taken = ports.free_port()
        held.bind(("127.0.0.1", taken))
        held.listen()
        monkeypatch.setattr(ports, "candidate_ranges", lambda low, high: [range(taken, taken + 1)])
        picked = ports.free_port(random.Random(0))  # the only candidate is taken: the kernel chooses instead
    assert picked != taken


def test_candidate_ranges_skip_the_ephemeral_range_and_narrow_gaps():
    assert ports.candidate_ranges(32768, 60999) == [range(10_000, 32768), range(61000, 65536)]
    assert ports.candidate_ranges(10_050, 65535) == []  # both gaps under 100 ports: the kernel chooses instead


def test_with_no_room_outside_the_range_the_kernel_chooses(monkeypatch):
    monkeypatch.setattr(ports, "ephemeral_range", lambda: (1024, 65535))
    assert ports.bindable(ports.free_port())
