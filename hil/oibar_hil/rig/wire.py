"""The serial cable between the host and the simulated MCU's pty, where link faults happen.

The host's session writes to and reads from :attr:`Wire.host_end` (a non-blocking transport);
once per lockstep exchange the rig moves the bytes across, so the MCU learns exactly how many
bytes to expect and every run is reproducible. Faults: the cable cut (link loss), bit errors
at a given bit-error rate (both directions), and a host that is not there (host crash).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class WireCounters:
    bytes_to_mcu: int = 0
    bytes_to_host: int = 0
    bytes_dropped: int = 0
    bits_flipped: int = 0


class _HostEnd:
    """What the host's LinkSession sees as its serial port."""

    def __init__(self, wire: "Wire") -> None:
        self._wire = wire

    def write(self, data: bytes) -> None:
        if self._wire.host_attached:
            self._wire.to_mcu += data

    def read(self) -> bytes:
        out = bytes(self._wire.to_host)
        self._wire.to_host.clear()
        return out


class Wire:
    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.to_mcu = bytearray()
        self.to_host = bytearray()
        self.cut = False
        self.ber = 0.0
        self.host_attached = True
        self.counters = WireCounters()
        self.host_end = _HostEnd(self)

    def _corrupt(self, data: bytes) -> bytes:
        if self.ber <= 0.0 or not data:
            return data
        n_bits = 8 * len(data)
        k = int(self.rng.binomial(n_bits, min(1.0, self.ber)))
        if k == 0:
            return data
        buf = bytearray(data)
        for bit in self.rng.choice(n_bits, size=k, replace=False):
            buf[bit // 8] ^= 1 << (bit % 8)
        self.counters.bits_flipped += k
        return bytes(buf)

    def take_to_mcu(self) -> bytes:
        """Bytes that reach the MCU's UART during the next exchange."""
        data = bytes(self.to_mcu)
        self.to_mcu.clear()
        if self.cut:
            self.counters.bytes_dropped += len(data)
            return b""
        data = self._corrupt(data)
        self.counters.bytes_to_mcu += len(data)
        return data

    def deliver_to_host(self, data: bytes) -> None:
        if self.cut or not self.host_attached:
            self.counters.bytes_dropped += len(data)
            return
        data = self._corrupt(data)
        self.counters.bytes_to_host += len(data)
        self.to_host += data
