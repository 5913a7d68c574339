"""Reading a flight log back with the ``mcap`` package: its messages in order, what it holds
(channels, counts, whether it was finished) and the run's summary."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from oibar.nav.flightlog.channels import CHANNELS
from oibar.nav.flightlog.errors import FlightLogError


@dataclass
class LogMessage:
    topic: str
    schema_name: str
    log_time: int
    data: bytes
    schema_id: int
    schema_data: bytes


def read_messages(path: str | Path, topics: Iterable[str] | None = None) -> Iterator[LogMessage]:
    """The messages of a flight log in the order they were written. A file cut short (the
    process was killed: no summary section) yields everything before the cut (``inspect_log``
    says whether the file was finished). FlightLogError when the file is missing or not an MCAP
    file."""
    from mcap.reader import NonSeekingReader

    path = Path(path)
    if not path.is_file():
        raise FlightLogError(f"{path}: flight log not found")
    wanted = set(topics) if topics is not None else None
    with open(path, "rb") as fh:
        reader = NonSeekingReader(fh, validate_crcs=True)
        it = reader.iter_messages(topics=list(wanted) if wanted else None, log_time_order=False)
        first = True
        while True:
            try:
                schema, channel, message = next(it)
            except StopIteration:
                return
            except Exception as exc:  # the parser's failure on a cut or foreign file, whatever its type
                if first:
                    raise FlightLogError(
                        f"{path}: not a readable MCAP file ({type(exc).__name__}: {exc})"
                    ) from exc
                return  # cut short: everything before the cut is good
            first = False
            yield LogMessage(
                channel.topic,
                schema.name if schema is not None else "",
                int(message.log_time),
                bytes(message.data),
                int(channel.schema_id),
                bytes(schema.data) if schema is not None else b"",
            )


@dataclass
class LogInventory:
    """What a flight log holds (``inspect_log``)."""

    path: Path
    channels: dict[str, str]  # topic -> schema name
    message_counts: dict[str, int]
    complete: bool  # finished by close(): the summary section is there
    size_bytes: int
    duration_s: float

    def missing(self, required: Iterable[str] = CHANNELS) -> list[str]:
        """Required topics without a message (or with another schema than ``CHANNELS``)."""
        out = []
        for topic in required:
            want = CHANNELS.get(topic)
            if self.message_counts.get(topic, 0) == 0:
                out.append(topic)
            elif want and self.channels.get(topic) != want:
                out.append(f"{topic} (schema {self.channels.get(topic)}, expected {want})")
        return out


def inspect_log(path: str | Path) -> LogInventory:
    """Open a flight log with the ``mcap`` reader: its channels, message counts and whether it
    was finished. FlightLogError when it cannot be read at all."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    path = Path(path)
    if not path.is_file():
        raise FlightLogError(f"{path}: flight log not found")
    size = path.stat().st_size
    try:
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
    except (McapError, EOFError, ValueError, OSError, KeyError):
        summary = None
    if summary is not None and summary.statistics is not None:
        st = summary.statistics
        channels = {
            ch.topic: (summary.schemas[ch.schema_id].name if ch.schema_id in summary.schemas else "")
            for ch in summary.channels.values()
        }
        counts: dict[str, int] = {}
        for cid, n in st.channel_message_counts.items():
            topic = summary.channels[cid].topic
            counts[topic] = counts.get(topic, 0) + int(n)
        dur = (st.message_end_time - st.message_start_time) / 1e9 if st.message_count else 0.0
        return LogInventory(path, channels, counts, True, size, dur)
    # no summary: the writer did not finish (killed); count by reading it through
    channels, counts = {}, {}
    t_min, t_max = None, None
    for m in read_messages(path):
        channels[m.topic] = m.schema_name
        counts[m.topic] = counts.get(m.topic, 0) + 1
        t_min = m.log_time if t_min is None else min(t_min, m.log_time)
        t_max = m.log_time if t_max is None else max(t_max, m.log_time)
    dur = (t_max - t_min) / 1e9 if t_min is not None and t_max is not None else 0.0
    return LogInventory(path, channels, counts, False, size, dur)


def read_summary(path: str | Path) -> dict[str, Any] | None:
    """The run's summary (``/run/summary``), None when the run did not write one."""
    import json

    found = None
    for m in read_messages(path, topics=["/run/summary"]):
        try:
            found = json.loads(m.data)
        except ValueError:
            continue
    return found if isinstance(found, dict) else None
