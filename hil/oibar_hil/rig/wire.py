"""The serial cable between the host and the simulated MCU's pty, where link faults happen.

The host's session writes to and reads from :attr:`Wire.host_end` (a non-blocking transport);
once per lockstep exchange the rig moves the bytes across, so the MCU learns exactly how many
bytes to expect and every run is reproducible. Faults: the cable cut (link loss), bit errors
at a given bit-error rate (both directions), and a host that is not there (host crash).

The wire also taps the host's frames like an eavesdropper would: it keeps the last
ARM_TRANSFER and START_TRANSFER frames byte for byte, which the ``replay`` fault sends again,
and reads the MCU's answers to them: a response with a new seq and a reason other than the
replay window's (NACK_STALE_SEQ / NACK_SEQ_REUSED) means the request reached the application
again (``replays_executed``; the cached answer to a retransmission keeps its original seq).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from oibar import pb
from oibar.link.framing import FrameDecoder

# Commands the tap records for the replay fault, by opcode.
RECORDED_OPCODES = (pb.CMD_ARM_TRANSFER, pb.CMD_START_TRANSFER)
# Answers that say the request did not reach the application.
_NOT_RUN = (pb.NACK_STALE_SEQ, pb.NACK_SEQ_REUSED, pb.NACK_NOT_CONNECTED)


@dataclass
class WireCounters:
    bytes_to_mcu: int = 0
    bytes_to_host: int = 0
    bytes_dropped: int = 0
    bits_flipped: int = 0
    replays_sent: int = 0
    replays_executed: int = 0


class _HostEnd:
    """What the host's LinkSession sees as its serial port."""

    def __init__(self, wire: Wire) -> None:
        self._wire = wire

    def write(self, data: bytes) -> None:
        if self._wire.host_attached:
            self._wire.to_mcu += data
            self._wire.tap(data)

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
        self.recorded: dict[int, bytes] = {}  # opcode -> the last such frame the host sent
        self._tap = FrameDecoder()
        self._ack_tap = FrameDecoder()
        self._runs: dict[int, set[int]] = {}  # recorded request seq -> seqs of responses that ran it

    def tap(self, data: bytes) -> None:
        """Record the host's ARM/START frames (the session writes one whole frame per call)."""
        packets = self._tap.feed(data)
        if (
            len(packets) == 1
            and packets[0].WhichOneof("body") == "command"
            and packets[0].command.opcode in RECORDED_OPCODES
        ):
            self.recorded[packets[0].command.opcode] = bytes(data)
            self._runs.setdefault(packets[0].seq, set())

    def _tap_answers(self, data: bytes) -> None:
        for p in self._ack_tap.feed(data):
            if p.WhichOneof("body") == "ack" and p.ack_seq in self._runs and p.ack.reason not in _NOT_RUN:
                runs = self._runs[p.ack_seq]
                runs.add(p.seq)
                self.counters.replays_executed = sum(max(0, len(r) - 1) for r in self._runs.values())

    def replay(self) -> int:
        """Send the recorded frames again, as they were; returns how many."""
        frames = [self.recorded[op] for op in RECORDED_OPCODES if op in self.recorded]
        for frame in frames:
            self.to_mcu += frame
        self.counters.replays_sent += len(frames)
        return len(frames)

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
        if self._runs:
            self._tap_answers(data)
