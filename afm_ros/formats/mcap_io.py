"""Session files: rosbag2-compatible MCAP writing, tolerant reading and crash recovery.

No ROS node here (only message modules and ``rclpy.serialization``), so the file logic is
testable without DDS. Layout written (the rosbag2 MCAP storage plugin's, ROS 2 Jazzy):

- header profile ``ros2``, library ``afm_ros <version>; mcap <version>``;
- one schema per message type, name ``pkg/msg/Type``, encoding ``ros2msg``, data = the full
  ``.msg`` text followed by every dependency as ``"\\n" + "=" * 80 + "\\nMSG: pkg/Type\\n" + text``
  (depth first, each dependency once, in rosbag2's order);
- one channel per topic, message encoding ``cdr``, metadata ``offered_qos_profiles`` (YAML list
  in rosbag2 Jazzy's format) and ``topic_type_hash`` (RIHS01 hash);
- messages: CDR bytes as received from the middleware, ``log_time`` = receive time and
  ``publish_time`` = the publisher's source timestamp, both wall clock [ns since the epoch].

Crash safety: the writer closes the current chunk and hands everything to the OS every
``flush_interval`` seconds, so a SIGKILL loses at most that much. A file is *complete* only when it
ends with the footer and the closing magic, which are written by :meth:`SessionWriter.close` alone
and never after a failed write. :func:`read_session` reads complete, truncated and damaged files,
taking the schemas and channels from the summary section when it is intact (so a damaged first
chunk loses only its own messages); :func:`recover` rewrites such a file into a complete one.
Budget: :class:`SessionWriter` keeps a file within ``max_size`` and the file system above
``min_free_space`` (:class:`BudgetReached`, the file can still be closed complete).

Command line: ``python -m afm_ros.formats.mcap_io info FILE`` and ``python -m
afm_ros.formats.mcap_io recover IN OUT``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import functools
import importlib
import io
import json
import os
import re
import stat
import struct
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, NamedTuple

from mcap import __version__ as _MCAP_VERSION
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.summary import Summary
from mcap.writer import CompressionType, Writer

MCAP_MAGIC = b"\x89MCAP0\r\n"
PROFILE = "ros2"
LIBRARY = f"afm_ros 0.1.0; mcap python {_MCAP_VERSION}"
DEFINITION_DELIMITER = "=" * 80
COMPRESSIONS = {
    "none": CompressionType.NONE,
    "lz4": CompressionType.LZ4,
    "zstd": CompressionType.ZSTD,
}
PARAMETER_METADATA_PREFIX = "afm_ros.parameters:"


class RecordingError(RuntimeError):
    """The session file cannot be created or written (message names the path and the cause)."""


class SessionFileError(RuntimeError):
    """A session file is missing, not MCAP, unreadable or has an unknown schema (names the
    file)."""


# --- message definitions, type hashes, QoS ------------------------------------------------

_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_PRIMITIVES = {
    "bool",
    "byte",
    "char",
    "float32",
    "float64",
    "int8",
    "uint8",
    "int16",
    "uint16",
    "int32",
    "uint32",
    "int64",
    "uint64",
    "string",
}


def _split_type(type_name: str) -> tuple[str, str, str]:
    parts = type_name.split("/")
    if len(parts) == 2:
        return parts[0], "msg", parts[1]
    if len(parts) == 3:
        return parts[0], parts[1], parts[2]
    raise ValueError(f"message type {type_name!r} is not of the form pkg/msg/Type")


def _share_dir(package: str) -> Path:
    from ament_index_python.packages import get_package_share_directory  # noqa: PLC0415 - formats: no ROS at load

    return Path(get_package_share_directory(package))


@functools.lru_cache(maxsize=None)
def _msg_text(type_name: str) -> str:
    pkg, ns, name = _split_type(type_name)
    path = _share_dir(pkg) / ns / f"{name}.msg"
    try:
        return path.read_text()
    except OSError as exc:
        raise ValueError(f"no .msg definition for {type_name} at {path}: {exc.strerror}") from exc


def _msg_dependencies(text: str, package: str) -> list[str]:
    deps = set()
    for m in _MSG_FIELD_TYPE.finditer(text):
        t = m.group(1)
        if t in _PRIMITIVES:
            continue
        deps.add(t if "/" in t else f"{package}/{t}")
    return sorted(deps)  # rosbag2 iterates a std::set (byte order)


@functools.lru_cache(maxsize=None)
def message_definition(type_name: str) -> str:
    """Full ``ros2msg`` definition of ``pkg/msg/Type`` as rosbag2 Jazzy stores it in a schema."""
    seen: set[str] = set()

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise ValueError(f"definition of {type_name} nests too deeply")
        text = _msg_text(name)
        result = text
        for dep in _msg_dependencies(text, _split_type(name)[0]):
            if dep not in seen:
                seen.add(dep)
                result += (
                    "\n" + DEFINITION_DELIMITER + "\nMSG: " + dep + "\n" + append(dep, depth - 1)
                )
        return result

    return append(type_name, 50)


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """The RIHS01 type hash of ``pkg/msg/Type`` from the rosidl-generated JSON, '' if unknown."""
    pkg, ns, name = _split_type(type_name)
    try:
        data = json.loads((_share_dir(pkg) / ns / f"{name}.json").read_text())
    except (OSError, ValueError, LookupError):
        return ""
    full = f"{pkg}/{ns}/{name}"
    for entry in data.get("type_hashes", []):
        if entry.get("type_name") == full:
            return entry.get("hash_string", "")
    return ""


@functools.lru_cache(maxsize=None)
def message_class(type_name: str):
    """Python message class of ``pkg/msg/Type``; SessionFileError-free ValueError if unknown."""
    pkg, ns, name = _split_type(type_name)
    try:
        return getattr(importlib.import_module(f"{pkg}.{ns}"), name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"message type {type_name} is not installed ({exc})") from exc


_INFINITE_NS = 9223372036854775807  # RMW_DURATION_INFINITE as rosbag2 Jazzy writes it


def _duration_yaml(ns: int, indent: str) -> str:
    ns = int(ns)
    if ns <= 0 or ns >= _INFINITE_NS:  # 0 = unspecified = infinite for these policies
        ns = _INFINITE_NS
    return f"{indent}  sec: {ns // 1_000_000_000}\n{indent}  nsec: {ns % 1_000_000_000}\n"


def qos_profiles_yaml(profiles: list) -> str:
    """``offered_qos_profiles`` text (rosbag2 Jazzy, metadata version 9) for rclpy QoSProfiles."""
    out = []
    for q in profiles:

        def name(policy):
            return policy.name.lower() if hasattr(policy, "name") else str(policy)

        out.append(
            f"- history: {name(q.history)}\n"
            f"  depth: {int(q.depth)}\n"
            f"  reliability: {name(q.reliability)}\n"
            f"  durability: {name(q.durability)}\n"
            f"  deadline:\n{_duration_yaml(q.deadline.nanoseconds, '  ')}"
            f"  lifespan:\n{_duration_yaml(q.lifespan.nanoseconds, '  ')}"
            f"  liveliness: {name(q.liveliness)}\n"
            "  liveliness_lease_duration:\n"
            f"{_duration_yaml(q.liveliness_lease_duration.nanoseconds, '  ')}"
            "  avoid_ros_namespace_conventions: "
            f"{'true' if q.avoid_ros_namespace_conventions else 'false'}"
        )
    return "\n".join(out)


def default_output_path(
    now: _dt.datetime | None = None,
    directory: str | os.PathLike | None = None,
    namespace: str = "/",
) -> Path:
    """``afm_session_[<namespace>_]YYYY_MM_DD-HH_MM_SS.mcap`` in ``directory`` (default: the
    current directory); the namespace (``/afm1`` -> ``afm1``, ``/lab/afm1`` -> ``lab_afm1``) keeps
    the files of instruments side by side apart. :class:`SessionWriter` with ``unique=True`` adds
    ``_2``, ``_3``... if the name is taken."""
    now = now or _dt.datetime.now()
    ns = "_".join(part for part in str(namespace).split("/") if part)
    return Path(directory or os.getcwd()) / now.strftime(
        f"afm_session_{ns + '_' if ns else ''}%Y_%m_%d-%H_%M_%S.mcap"
    )


# --- writer ------------------------------------------------------------------------------


def free_space(path: str | os.PathLike) -> int:
    """Bytes an unprivileged user may still write on the file system of ``path`` (a directory)."""
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def _record_length(record) -> int:
    """Bytes ``record`` (an mcap.records object) takes in a file, with its opcode and length."""
    builder = RecordBuilder()
    record.write(builder)
    return builder.count


class BudgetReached(Exception):
    """The next message would take the file beyond ``max_size`` or the file system below
    ``min_free_space``; nothing of it was written and the file can still be closed complete."""

    def __init__(self, limit: str, text: str):
        super().__init__(text)
        self.limit = limit  # 'max_size' or 'min_free_space'


# bounds used to keep a file within its budget (see SessionWriter.size_bound) [B]
_MESSAGE_OVERHEAD = 31 + 16  # message record header and fields + its message index entry
_CHUNK_OVERHEAD = 1024  # chunk record fields + compressor frame headers
_INDEX_PER_CHANNEL = (
    15 + 10
)  # a message index record's header per channel and chunk + its chunk index entry
_SUMMARY_FIXED = (
    13 + 55 + 6 * 26 + 29 + len(MCAP_MAGIC) + 256
)  # data end, statistics, offsets, footer, magic, margin
_PER_CHUNK_INDEX = 96  # a chunk index record without its per-channel entries


class SessionWriter:
    """Append-only rosbag2-layout MCAP writer with periodic flushing and fail-stop errors.

    Every OSError (full disk, I/O error) turns into :class:`RecordingError` naming the path; after
    the first failure nothing more is written, in particular never a footer, so a damaged file
    never claims to be complete.

    Budget: with ``max_size`` [B] > 0 the closed file (summary and footer included) never exceeds
    it, and with ``min_free_space`` [B] > 0 the file system keeps at least that much free: before a
    message would break either, :meth:`write` raises :class:`BudgetReached` without writing it, and
    :meth:`close` still makes a complete file of everything before. Below ``min_free_space`` at the
    start, the file is not created (RecordingError). ``unique``: if ``path`` exists, the first free
    ``<stem>_2.mcap``, ``<stem>_3.mcap``... is created instead (otherwise RecordingError).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        compression: str = "zstd",
        chunk_size: int = 4 << 20,
        unique: bool = False,
        max_size: float = 0,
        min_free_space: float = 0,
    ):
        self.path = Path(path).absolute()
        if compression not in COMPRESSIONS:
            raise ValueError(
                f"compression={compression!r} is not allowed; allowed: {', '.join(COMPRESSIONS)}"
            )
        parent = self.path.parent
        if not parent.is_dir():
            raise RecordingError(
                f"cannot record to {self.path}: directory {parent} does not exist "
                "or is not a directory"
            )
        self.max_size = int(max_size)
        self.min_free_space = int(min_free_space)
        if self.min_free_space:
            free = free_space(parent)
            if free < self.min_free_space:
                raise RecordingError(
                    f"cannot record to {self.path}: its file system has {free:.3g} B free, below "
                    f"min_free_space {self.min_free_space:.3g} B (free disk space, record "
                    "elsewhere, or lower "
                    "min_free_space; 0 = no check)"
                )
        self._stream = self._create(unique)
        self.error: RecordingError | None = None
        self.closed = False
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.message_count = 0
        self.bytes_written = 0  # [B] handed to the file so far (summary not included until closed)
        self._pending = 0  # [B] records in the open chunk, with their message index entries
        self._chunks = 0  # chunks written
        self._summary_bytes = _SUMMARY_FIXED  # [B] bound of the summary section and footer
        self._free_checked: tuple[int, int] | None = (
            None  # (free bytes, bytes_written) at the last check
        )
        self._writer = Writer(
            self._stream, chunk_size=chunk_size, compression=COMPRESSIONS[compression]
        )
        self._guard(
            lambda: (self._writer.start(profile=PROFILE, library=LIBRARY), self._stream.flush())
        )
        self.bytes_written = self._stream.tell()

    def _create(self, unique: bool):
        """Open a new file exclusively (never overwrite); with ``unique``, the first free ``_N``
        name."""
        candidate = self.path
        for n in range(2, 10_000):
            try:
                stream = open(candidate, "xb")
                self.path = candidate
                return stream
            except FileExistsError:
                if not unique:
                    raise RecordingError(
                        f"cannot record to {self.path}: the file already exists "
                        "(choose another output path)"
                    ) from None
                candidate = self.path.with_name(f"{self.path.stem}_{n}{self.path.suffix}")
            except OSError as exc:
                raise RecordingError(
                    f"cannot record to {candidate}: {exc.strerror or exc}"
                ) from exc
        raise RecordingError(f"cannot record to {self.path}: it and 9998 numbered variants exist")

    def _guard(self, fn):
        if self.error is not None:
            raise self.error
        if self.closed:
            raise RecordingError(f"{self.path} is already closed")
        try:
            return fn()
        except OSError as exc:
            self._failed(exc)

    def _failed(self, exc: OSError):
        why = os.strerror(exc.errno) if exc.errno else str(exc)
        self.error = RecordingError(
            f"writing {self.path} failed: {why}; recording stopped, the file is incomplete "
            f"(no summary or footer; read what was flushed with "
            f"`python -m afm_ros.formats.mcap_io recover {self.path} OUT.mcap`)"
        )
        self.error.errno = exc.errno
        self._abandon()
        raise self.error from exc

    def _abandon(self):
        try:
            self._stream.close()
        except OSError:
            try:  # the buffered bytes cannot be written; drop them with the descriptor
                os.close(self._stream.fileno())
            except (OSError, ValueError):
                pass
        self.closed = True

    def add_channel(
        self,
        topic: str,
        type_name: str,
        offered_qos_profiles: str = "",
        topic_type_hash: str | None = None,
    ) -> int:
        """Register ``topic`` (schema created once per type) and return its channel id."""
        if topic in self._channels:
            return self._channels[topic]
        if type_name not in self._schemas:
            data = message_definition(type_name).encode()
            grown = _record_length(
                Schema(id=0, name=type_name, encoding="ros2msg", data=data)
            )  # in the open chunk and the summary
            self._schemas[type_name] = self._guard(
                lambda: self._track(
                    lambda: self._writer.register_schema(type_name, "ros2msg", data), grown
                )
            )
            self._summary_bytes += grown
        metadata = {"offered_qos_profiles": offered_qos_profiles}
        h = type_hash(type_name) if topic_type_hash is None else topic_type_hash
        if h:
            metadata["topic_type_hash"] = h
        grown = _record_length(
            Channel(id=0, topic=topic, message_encoding="cdr", schema_id=0, metadata=metadata)
        )
        cid = self._guard(
            lambda: self._track(
                lambda: self._writer.register_channel(
                    topic, "cdr", self._schemas[type_name], metadata
                ),
                grown,
            )
        )
        self._channels[topic] = cid
        self._summary_bytes += grown + 10  # + its statistics entry
        return cid

    def _track(self, fn, grown: int):
        """Run a Writer call that adds ``grown`` bytes of records to the open chunk, and account
        for the chunk it may have closed (then the file grew and the chunk holds those records)."""
        before = self.bytes_written
        result = fn()
        self.bytes_written = self._stream.tell()
        if self.bytes_written != before:
            self._chunks += 1
            self._pending = 0
        else:
            self._pending += grown
        return result

    def size_bound(self, extra: int = 0, outside: bool = False) -> int:
        """Upper bound [B] of the closed file if ``extra`` more bytes of records joined the open
        chunk (``outside``: were written outside it): what is written, the open chunk compressed
        (zstd/lz4 grow incompressible data by < 1/64) with its message indexes, every chunk's index
        entry, the repeated schemas and channels, and the rest of the summary, footer and magic."""
        n = self._pending + (0 if outside else extra)
        per_chunk = _PER_CHUNK_INDEX + _INDEX_PER_CHANNEL * len(self._channels)
        return (
            self.bytes_written
            + (extra if outside else 0)
            + (n + n // 64 + _CHUNK_OVERHEAD + per_chunk if n else 0)
            + self._summary_bytes
            + per_chunk * self._chunks
        )

    def _over_budget(self, extra: int, outside: bool = False) -> BudgetReached | None:
        bound = self.size_bound(extra, outside)
        if self.max_size and bound > self.max_size:
            return BudgetReached("max_size", f"max_size {self.max_size:.3g} B reached")
        if self.min_free_space:
            if self._free_checked is None or self._free_checked[1] != self.bytes_written:
                self._free_checked = (free_space(self.path.parent), self.bytes_written)
            free, at = self._free_checked
            left = free - (bound - at)  # free space once everything up to the footer is written
            if left < self.min_free_space:
                return BudgetReached(
                    "min_free_space",
                    f"min_free_space {self.min_free_space:.3g} B reached (the file "
                    f"system has {free - (self.bytes_written - at):.3g} B free)",
                )
        return None

    def write(
        self,
        channel_id: int,
        data: bytes,
        log_time: int,
        publish_time: int | None = None,
        sequence: int = 0,
    ) -> None:
        """Append one CDR message; times in ns (wall clock, see module doc). Raises BudgetReached
        (nothing written) if the message would break the budget even after closing the open
        chunk."""
        if self.error is not None or self.closed:
            self._guard(lambda: None)  # raises the stored error
        size = _MESSAGE_OVERHEAD + len(data)
        if (self.max_size or self.min_free_space) and self._over_budget(size) is not None:
            if (
                self._pending
            ):  # the bound assumes incompressible data: close the chunk to know its size
                self.flush()
            stop = self._over_budget(size)
            if (
                stop is None
                and self.max_size
                and self.max_size - self.size_bound(size) < self.max_size // 100
            ):
                # within 1 % of max_size: stop rather than close ever smaller chunks
                stop = BudgetReached(
                    "max_size", f"max_size {self.max_size:.3g} B reached (within 1 %)"
                )
            if stop is not None:
                raise stop
        try:
            self._track(
                lambda: self._writer.add_message(
                    channel_id,
                    log_time,
                    data,
                    log_time if publish_time is None else publish_time,
                    sequence,
                ),
                size,
            )
        except OSError as exc:
            self._failed(exc)
        self.message_count += 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record (written at once, outside the chunks); counts against the budget too
        (BudgetReached, nothing written, if it would break it)."""
        record = Metadata(name=name, metadata={str(k): str(v) for k, v in data.items()})
        size = _record_length(record)
        index = 9 + 8 + 8 + 4 + len(name.encode())  # its metadata index in the summary
        if self.max_size or self.min_free_space:
            stop = self._over_budget(size + index, outside=True)
            if stop is not None:
                raise stop
        self._guard(lambda: self._writer.add_metadata(record.name, record.metadata))
        self.bytes_written = self._stream.tell()
        self._summary_bytes += index

    def flush(self) -> None:
        """Close the current chunk and hand everything to the OS (survives a process kill)."""
        self._guard(lambda: self._track(self._writer.flush, 0))

    def close(self) -> None:
        """Write summary, index and footer (only if nothing failed) and close the file."""
        if self.closed:
            return
        self._guard(self._writer.finish)
        self.bytes_written = self._guard(self._stream.tell)
        self._guard(self._stream.close)
        self.closed = True


# --- reader ------------------------------------------------------------------------------


@dataclass
class SessionMessage:
    topic: str
    type_name: str
    data: bytes
    log_time: int  # [ns]
    publish_time: int  # [ns]
    sequence: int
    channel_id: int


class Damage(NamedTuple):
    """One skipped region of a session file."""

    offset: int  # [B] from the start of the file
    length: int  # [B]
    reason: str
    chunk: tuple[int, int] | None = None  # (number from 1, chunks listed in the summary), if known
    messages: int | None = None  # messages the region held (from its message index), if known

    def text(self) -> str:
        where = f"chunk {self.chunk[0]} of {self.chunk[1]}" if self.chunk else "a region"
        held = (
            f"{self.messages} messages"
            if self.messages is not None
            else "an unknown number of messages"
        )
        return (
            f"{where} at byte {self.offset} ({self.length} bytes, {self.reason}): "
            f"{held} lost there"
        )


@dataclass
class SessionScan:
    """What a tolerant read of a session file found."""

    path: Path
    complete: bool = False  # footer and closing magic present and the data section read fully
    truncated_reason: str = ""  # why reading stopped early ('' if it did not)
    bytes_read: int = 0  # offset up to which records were intact
    file_size: int = 0
    schemas: dict = field(default_factory=dict)  # id -> Schema
    channels: dict = field(default_factory=dict)  # id -> Channel
    metadata: list = field(default_factory=list)  # Metadata records
    message_counts: dict = field(default_factory=dict)  # topic -> count
    header: Header | None = None
    compression: str = ""
    damaged: list = field(default_factory=list)  # Damage of every skipped region
    skipped_messages: int = (
        0  # messages in skipped chunks (from their message indexes, where intact)
    )
    chunks: int = 0  # intact chunks read
    summary: Summary | None = (
        None  # the file's summary section (CRC checked), if it has an intact one
    )
    summary_problem: str = ""  # why the summary section was not used ('' if used or absent)
    messages_read: int = 0  # intact messages of every topic (whatever the topic filter)
    orphan_messages: int = (
        0  # intact messages whose channel definition was lost (no summary to read it from)
    )
    footer_read: bool = False  # the data section was read up to an intact footer

    @property
    def all_read(self) -> bool:
        """Every message the file's writer wrote was read (at most the closing magic is
        missing)."""
        return self.footer_read and not self.damaged and not self.orphan_messages

    @property
    def expected_messages(self) -> int | None:
        """Messages the summary's statistics list (None without a summary)."""
        stats = self.summary.statistics if self.summary is not None else None
        return stats.message_count if stats is not None else None

    def expected_counts(self) -> dict[str, int]:
        """topic -> messages listed in the summary's statistics (empty without a summary)."""
        stats = self.summary.statistics if self.summary is not None else None
        if stats is None:
            return {}
        out: dict[str, int] = {}
        for cid, n in stats.channel_message_counts.items():
            ch = self.channels.get(cid)
            if ch is not None:
                out[ch.topic] = out.get(ch.topic, 0) + n
        return out

    @property
    def damage_text(self) -> str:
        """One sentence on the damage met ('' if none)."""
        if not self.damaged and not self.orphan_messages:
            return ""
        size = sum(d.length for d in self.damaged)
        parts = [d.text() for d in self.damaged[:3]]
        if len(self.damaged) > 3:
            parts.append(
                f"{len(self.damaged) - 3} more ({self.skipped_messages} messages lost in all)"
            )
        total = f" ({size} bytes in all)" if len(self.damaged) > 1 else ""
        text = f"{len(self.damaged)} damaged region(s) skipped{total}: " + "; ".join(parts)
        if self.orphan_messages:
            text += (
                f"; {self.orphan_messages} messages of intact chunks could not be read either: "
                "the "
                "definitions of their topics were in the damaged part and the file has no summary"
            )
        else:
            text += "; every other chunk was read"
        expected = self.expected_messages
        if expected is not None and self.bytes_read >= self.file_size - len(MCAP_MAGIC):
            text += f" ({self.messages_read} of the {expected} messages the summary lists)"
        return text

    @property
    def topics(self) -> dict[str, str]:
        """topic -> type name."""
        return {
            c.topic: self.schemas[c.schema_id].name if c.schema_id in self.schemas else ""
            for c in self.channels.values()
        }


def check_mcap_file(path: str | os.PathLike) -> Path:
    """Raise SessionFileError unless ``path`` is a regular file that starts with the MCAP magic."""
    p = Path(path)
    if not p.exists():
        raise SessionFileError(f"session file {p} does not exist")
    if p.is_dir():
        raise SessionFileError(f"session file {p} is a directory, not an .mcap file")
    mode = p.stat().st_mode
    if not stat.S_ISREG(mode):
        kind = (
            "a FIFO"
            if stat.S_ISFIFO(mode)
            else "a device"
            if (stat.S_ISCHR(mode) or stat.S_ISBLK(mode))
            else "a socket"
            if stat.S_ISSOCK(mode)
            else "not a regular file"
        )
        raise SessionFileError(
            f"session file {p} is {kind}, not a regular .mcap file (it could block forever)"
        )
    try:
        with open(p, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise SessionFileError(f"cannot read session file {p}: {exc.strerror}") from exc
    if head != MCAP_MAGIC:
        what = "empty" if not head else f"starts with {head[:8]!r}"
        raise SessionFileError(
            f"{p} is not an MCAP file ({what}; expected the MCAP magic {MCAP_MAGIC!r})"
        )
    return p


_OPCODES = {o.value for o in Opcode}
_RECORD_CLASSES = {
    Opcode.HEADER: Header,
    Opcode.FOOTER: Footer,
    Opcode.SCHEMA: Schema,
    Opcode.CHANNEL: Channel,
    Opcode.CHUNK: Chunk,
    Opcode.MESSAGE_INDEX: MessageIndex,
    Opcode.METADATA: Metadata,
}
_RESYNC_WINDOW = 64 << 20  # how far past a damaged record header to look for the next record [B]
_SUMMARY_LIMIT = (
    64 << 20
)  # largest summary section read [B]: an hour of 1 s chunks needs ~8 MB; a flipped bit in
# the footer must not make every reader allocate its claim before the CRC can refute it


def _parse(opcode: int, body: bytes):
    cls = _RECORD_CLASSES.get(opcode)
    if cls is None:
        return None
    stream = ReadDataStream(io.BytesIO(body))
    return cls.read(stream, len(body)) if cls is Message else cls.read(stream)


def _plausible_record_at(f, pos: int, size: int) -> bool:
    """A record header at ``pos`` whose end is the file end or another record header."""
    f.seek(pos)
    head = f.read(9)
    if len(head) < 9 or head[0] not in _OPCODES:
        return False
    end = pos + 9 + struct.unpack_from("<Q", head, 1)[0]
    if end > size:
        return False
    if end == size or end + len(MCAP_MAGIC) == size:
        return True
    f.seek(end)
    nxt = f.read(1)
    return bool(nxt) and nxt[0] in _OPCODES


_RESYNC_OPCODES = frozenset(
    (
        Opcode.CHUNK,
        Opcode.MESSAGE_INDEX,
        Opcode.DATA_END,
        Opcode.CHANNEL,
        Opcode.SCHEMA,
        Opcode.METADATA,
        Opcode.MESSAGE,
    )
)


def _resync(f, start: int, size: int) -> int | None:
    """Offset of the next plausible record after damage at ``start`` (None: none found)."""
    pos = start + 1
    limit = min(size, start + _RESYNC_WINDOW)
    while pos < limit:
        f.seek(pos)
        block = f.read(min(1 << 20, limit - pos) + 9)
        n = min(len(block), limit - pos)
        for k in range(n):
            if block[k] not in _RESYNC_OPCODES:
                continue
            if k + 9 <= len(block):  # reject the (typical) random length without touching the file
                end = pos + k + 9 + struct.unpack_from("<Q", block, k + 1)[0]
                if end > size:
                    continue
            if _plausible_record_at(f, pos + k, size):
                return pos + k
        pos += n
    return None


_FOOTER_HEAD = bytes([Opcode.FOOTER]) + struct.pack(
    "<Q", 20
)  # opcode and length of every Footer record
_SUMMARY_CLASSES = {
    Opcode.SCHEMA: Schema,
    Opcode.CHANNEL: Channel,
    Opcode.STATISTICS: Statistics,
    Opcode.CHUNK_INDEX: ChunkIndex,
    Opcode.METADATA_INDEX: MetadataIndex,
}


def _read_summary(f, size: int) -> tuple[Summary | None, str]:
    """The summary section (schemas, channels, statistics, chunk and metadata indexes) found
    through the footer at the end of the file, CRC checked; ``(None, why)`` if there is none or it
    is damaged.

    MCAP writers repeat every schema and channel there, so a reader that lost the data-section copy
    (in a damaged chunk) still knows every topic. The footer is looked for in the last bytes, so a
    file whose closing magic is cut short still has its summary read.
    """
    tail_len = min(size, 64)
    f.seek(size - tail_len)
    tail = f.read(tail_len)
    at = tail.rfind(_FOOTER_HEAD)
    if at < 0 or at + 29 > len(tail):
        return None, "no footer"
    footer_pos = size - tail_len + at
    summary_start, offset_start, crc = struct.unpack_from("<QQI", tail, at + 9)
    if summary_start == 0:
        return None, "the file has no summary section"
    if (
        not len(MCAP_MAGIC) <= summary_start < footer_pos
        or footer_pos - summary_start > _SUMMARY_LIMIT
    ):
        return None, f"the footer points to a summary at byte {summary_start}, outside the file"
    f.seek(summary_start)
    body = f.read(footer_pos - summary_start)
    if crc:
        calc = zlib.crc32(body)
        calc = zlib.crc32(_FOOTER_HEAD + struct.pack("<QQ", summary_start, offset_start), calc)
        if calc != crc:
            return None, "the summary section is damaged (CRC mismatch)"
    summary = Summary()
    pos = 0
    try:
        while pos + 9 <= len(body):
            opcode, length = body[pos], struct.unpack_from("<Q", body, pos + 1)[0]
            cls = _SUMMARY_CLASSES.get(opcode)
            if cls is not None:
                rec = cls.read(ReadDataStream(io.BytesIO(body[pos + 9 : pos + 9 + length])))
                if cls is Schema:
                    summary.schemas[rec.id] = rec
                elif cls is Channel:
                    summary.channels[rec.id] = rec
                elif cls is Statistics:
                    summary.statistics = rec
                elif cls is ChunkIndex:
                    summary.chunk_indexes.append(rec)
                else:
                    summary.metadata_indexes.append(rec)
            pos += 9 + length
    except Exception as exc:  # noqa: BLE001 - an unparsable summary is not used
        return None, f"the summary section is unreadable ({type(exc).__name__})"
    summary.chunk_indexes.sort(key=lambda c: c.chunk_start_offset)
    return summary, ""


def read_summary(path: str | os.PathLike) -> Summary | None:
    """The file's summary section (see :func:`_read_summary`), or None if it has no intact one."""
    p = check_mcap_file(path)
    with open(p, "rb") as f:
        return _read_summary(f, p.stat().st_size)[0]


def _chunk_number(summary: Summary | None, start: int, end: int) -> tuple[int, int] | None:
    """(number from 1, total) of the summary's chunk that overlaps the byte range [start, end)."""
    if summary is None:
        return None
    for k, c in enumerate(summary.chunk_indexes):
        if c.chunk_start_offset < end and start < c.chunk_start_offset + c.chunk_length:
            return k + 1, len(summary.chunk_indexes)
    return None


def read_session(
    path: str | os.PathLike, scan: SessionScan | None = None, topics: set[str] | None = None
) -> Iterator[SessionMessage]:
    """Yield every readable message in file order (complete, truncated or damaged file).

    ``scan`` (optional) is filled while reading: schemas, channels, metadata, counts and, once the
    generator is exhausted, whether the file was complete, why reading stopped early, and every
    damaged region it skipped. Schemas and channels are taken first from the summary section
    (where the writer repeats them), so a damaged chunk that held their first copies loses only
    its own messages. Every chunk carries its own length and CRC: a chunk that fails them is
    skipped (its message index, if intact, says how many messages it held) and reading goes on
    with the next record; a damaged record header is skipped by finding the next plausible record.
    A file is complete only with its footer and the closing magic.
    Raises SessionFileError for a missing, non-regular or non-MCAP file.
    """
    p = check_mcap_file(path)
    scan = scan if scan is not None else SessionScan(p)
    scan.path = p
    size = scan.file_size = p.stat().st_size
    saw_footer = False
    skipped_chunk_end = None  # end of the last skipped chunk: its message indexes follow it
    with open(p, "rb") as f:
        scan.summary, scan.summary_problem = _read_summary(f, size)
        if scan.summary is not None:
            scan.schemas.update(scan.summary.schemas)
            scan.channels.update(scan.summary.channels)
        pos = len(MCAP_MAGIC)
        scan.bytes_read = pos
        while pos < size:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                if not (saw_footer or head == MCAP_MAGIC[: len(head)]):
                    scan.truncated_reason = (
                        f"file ends inside a record header at byte {pos} of {size}"
                    )
                break
            opcode, length = head[0], struct.unpack_from("<Q", head, 1)[0]
            end = pos + 9 + length
            if opcode not in _OPCODES or end > size:
                if opcode in _OPCODES and _resync(f, pos, size) is None:
                    scan.truncated_reason = (
                        f"file ends inside a record: intact up to byte {pos} of {size} "
                        f"(a {Opcode(opcode).name.lower()} record of {length} bytes)"
                    )
                    break
                nxt = _resync(f, pos, size)
                reason = f"unreadable record header (opcode {opcode:#04x})"
                if nxt is None:
                    scan.damaged.append(
                        Damage(pos, size - pos, reason, _chunk_number(scan.summary, pos, size))
                    )
                    scan.truncated_reason = f"damaged at byte {pos}: no intact record after it"
                    break
                scan.damaged.append(
                    Damage(pos, nxt - pos, reason, _chunk_number(scan.summary, pos, nxt))
                )
                pos = nxt
                continue
            f.seek(pos + 9)
            body = f.read(length)
            try:
                record = _parse(opcode, body)
                inner = (
                    breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else None
                )
            except Exception as exc:  # noqa: BLE001 - any parser error is damage of this record
                reason = f"{type(exc).__name__}: {exc}".strip(": ")
                is_chunk = opcode == Opcode.CHUNK
                scan.damaged.append(
                    Damage(
                        pos,
                        end - pos,
                        f"{'chunk' if is_chunk else 'record'} {reason[:200]}",
                        _chunk_number(scan.summary, pos, end) if is_chunk else None,
                        None if is_chunk else 0,
                    )
                )
                skipped_chunk_end = end if is_chunk else None
                pos = end
                continue
            if inner is not None:
                scan.chunks += 1
                skipped_chunk_end = None
                records = inner
            elif isinstance(record, MessageIndex):
                if skipped_chunk_end is not None:  # the index of a skipped chunk: what was lost
                    scan.skipped_messages += len(record.records)
                    last = scan.damaged[-1]
                    scan.damaged[-1] = last._replace(
                        messages=(last.messages or 0) + len(record.records)
                    )
                records = []
            else:
                records = [record] if record is not None else []
            for rec in records:
                if isinstance(rec, Message):
                    ch = scan.channels.get(rec.channel_id)
                    if ch is None:
                        scan.orphan_messages += 1
                        continue
                    scan.messages_read += 1
                    if topics is not None and ch.topic not in topics:
                        continue
                    scan.message_counts[ch.topic] = scan.message_counts.get(ch.topic, 0) + 1
                    schema = scan.schemas.get(ch.schema_id)
                    yield SessionMessage(
                        ch.topic,
                        schema.name if schema else "",
                        rec.data,
                        rec.log_time,
                        rec.publish_time,
                        rec.sequence,
                        rec.channel_id,
                    )
                elif isinstance(rec, Channel):
                    scan.channels.setdefault(rec.id, rec)
                elif isinstance(rec, Schema):
                    scan.schemas.setdefault(rec.id, rec)
                elif isinstance(rec, Metadata):
                    scan.metadata.append(rec)
                elif isinstance(rec, Header):
                    scan.header = rec
                elif isinstance(rec, Footer):
                    saw_footer = True
            pos = end
            scan.bytes_read = pos
            if saw_footer:
                f.seek(pos)
                closing = f.read(len(MCAP_MAGIC) + 1)
                if closing != MCAP_MAGIC:
                    scan.truncated_reason = (
                        f"the file is truncated: it ends {len(MCAP_MAGIC) - len(closing)} byte(s) "
                        "before the end "
                        f"of its closing magic (every record up to the footer is intact)"
                        if MCAP_MAGIC.startswith(closing)
                        else f"the closing magic after the footer at byte {pos} is damaged or "
                        "followed by extra bytes"
                    )
                break
    if not scan.truncated_reason and not saw_footer:
        scan.truncated_reason = "no footer (the recorder did not close the file)"
    if (scan.damaged or scan.orphan_messages) and not scan.truncated_reason:
        scan.truncated_reason = scan.damage_text
    elif scan.damaged or scan.orphan_messages:
        scan.truncated_reason += "; " + scan.damage_text
    scan.footer_read = saw_footer
    scan.complete = (
        saw_footer
        and not scan.damaged
        and not scan.orphan_messages
        and scan.truncated_reason == ""
    )


def scan_session(path: str | os.PathLike) -> SessionScan:
    """Read the whole file once and return what it holds (counts per topic, completeness)."""
    scan = SessionScan(Path(path))
    for _ in read_session(path, scan):
        pass
    return scan


def _scan_compression(path: Path) -> str:
    with open(path, "rb") as f:
        for record in StreamReader(f, emit_chunks=True).records:
            if type(record).__name__ == "Chunk":
                return record.compression or "none"
    return "zstd"


def serialize_exact(msg) -> bytes:
    """CDR bytes of ``msg`` via ``rclpy.serialization``, cut to the true serialized length.

    rmw_fastrtps' serialize_message (Jazzy) can return a few bytes of uninitialised buffer after
    the message (seen for rcl_interfaces/msg/ParameterEvent); strict readers (rosbags) reject
    that. Deserialisation of a shorter prefix fails, so the shortest prefix that deserialises is
    the message (found by bisection).
    """
    from rclpy.serialization import deserialize_message, serialize_message  # noqa: PLC0415 - no ROS at load

    data = serialize_message(msg)
    cls = type(msg)
    lo, hi = 4, len(data)  # hi always deserialises
    while lo < hi:
        mid = (lo + hi) // 2
        try:
            deserialize_message(data[:mid], cls)
            hi = mid
        except Exception:
            lo = mid + 1
    return data[:hi]


def decode(message: SessionMessage):
    """Deserialize a recorded message with rclpy (ValueError if its type is not installed)."""
    from rclpy.serialization import deserialize_message  # noqa: PLC0415 - formats: no ROS at load

    return deserialize_message(message.data, message_class(message.type_name))


@dataclass
class RecoverResult:
    input: Path
    output: Path
    messages: int
    complete_input: bool
    reason: str
    bytes_read: int
    input_size: int
    last_log_time: int


def recover(
    src: str | os.PathLike, dst: str | os.PathLike, compression: str | None = None
) -> RecoverResult:
    """Copy every intact record of ``src`` (typically a killed recording) into a complete file
    ``dst``."""
    src_path = check_mcap_file(src)
    if compression is None:
        try:
            compression = _scan_compression(src_path)
        except Exception:  # damaged first chunk: fall back to the default
            compression = "zstd"
        compression = "none" if compression == "" else compression
        if compression not in COMPRESSIONS:
            compression = "zstd"
    scan = SessionScan(src_path)
    out = SessionWriter(dst, compression=compression)
    written_channels: dict[int, int] = {}
    count = 0
    last = 0
    try:
        for m in read_session(src_path, scan):
            cid = written_channels.get(m.channel_id)
            if cid is None:
                ch = scan.channels[m.channel_id]
                schema = scan.schemas.get(ch.schema_id)
                if schema is None:
                    continue
                if schema.name not in out._schemas:
                    out._schemas[schema.name] = out._guard(
                        lambda: out._writer.register_schema(
                            schema.name, schema.encoding, schema.data
                        )
                    )
                cid = out._guard(
                    lambda: out._writer.register_channel(
                        ch.topic, ch.message_encoding, out._schemas[schema.name], dict(ch.metadata)
                    )
                )
                written_channels[m.channel_id] = cid
            out.write(cid, m.data, m.log_time, m.publish_time, m.sequence)
            count += 1
            last = max(last, m.log_time)
        for md in scan.metadata:
            out.add_metadata(md.name, md.metadata)
        out.add_metadata(
            "afm_ros.recovered",
            {
                "source": str(src_path),
                "source_complete": str(scan.complete).lower(),
                "reason": scan.truncated_reason,
                "bytes_read": str(scan.bytes_read),
                "source_size": str(scan.file_size),
            },
        )
        out.close()
    except BaseException:
        if not out.closed:
            out._abandon()
        raise
    return RecoverResult(
        src_path,
        out.path,
        count,
        scan.complete,
        scan.truncated_reason,
        scan.bytes_read,
        scan.file_size,
        last,
    )


def parameter_metadata(scan: SessionScan) -> dict[str, dict[str, str]]:
    """Initial parameter snapshots stored as metadata records: node -> {name: YAML value}."""
    out = {}
    for md in scan.metadata:
        if md.name.startswith(PARAMETER_METADATA_PREFIX):
            out[md.name[len(PARAMETER_METADATA_PREFIX) :]] = dict(md.metadata)
    return out


# --- command line ------------------------------------------------------------------------


def _info(path: str) -> int:
    scan = scan_session(path)
    print(f"file: {scan.path} ({scan.file_size} bytes)")
    print(f"complete: {'yes' if scan.complete else 'no - ' + scan.truncated_reason}")
    if scan.header is not None:
        print(f"profile: {scan.header.profile}  library: {scan.header.library}")
    if scan.summary is not None:
        print(
            f"summary: {len(scan.summary.channels)} topics, {len(scan.summary.chunk_indexes)} "
            "chunks"
            + (
                f", {scan.expected_messages} messages"
                if scan.expected_messages is not None
                else ""
            )
        )
    elif scan.summary_problem:
        print(
            f"summary: not used ({scan.summary_problem}); topics and counts from the data section"
        )
    for d in scan.damaged:
        print(f"damaged: {d.text()}")
    expected = scan.expected_counts()
    read = sum(scan.message_counts.values())
    if scan.expected_messages is not None and read != scan.expected_messages:
        print(
            f"messages: {read} read of {scan.expected_messages} ({scan.expected_messages - read} "
            "lost)"
        )
    else:
        print(
            f"messages: {read}"
            + (
                f" ({scan.orphan_messages} more in intact chunks without their topic definitions)"
                if scan.orphan_messages
                else ""
            )
        )
    for topic, type_name in sorted(scan.topics.items()):
        n = scan.message_counts.get(topic, 0)
        of = f" of {expected[topic]}" if topic in expected and expected[topic] != n else ""
        print(f"  {topic:40s} {type_name:36s} {n:8d} msgs{of}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m afm_ros.formats.mcap_io",
        description="Inspect or recover afm_ros session files (.mcap).",
    )
    sub = parser.add_subparsers(dest="cmd", required=True)
    p_info = sub.add_parser(
        "info", help="topics, message counts and completeness of a session file"
    )
    p_info.add_argument("file")
    p_rec = sub.add_parser(
        "recover", help="copy the intact part of a truncated session into a complete file"
    )
    p_rec.add_argument("input")
    p_rec.add_argument("output")
    p_rec.add_argument("--compression", choices=list(COMPRESSIONS), default=None)
    args = parser.parse_args(argv)
    try:
        if args.cmd == "info":
            return _info(args.file)
        res = recover(args.input, args.output, args.compression)
    except (SessionFileError, RecordingError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `info FILE | head`
        sys.stdout = None
        return 0
    state = "was complete" if res.complete_input else f"was incomplete ({res.reason})"
    print(
        f"recovered {res.messages} messages from {res.input} ({state}; {res.bytes_read} of "
        f"{res.input_size} bytes intact) into {res.output}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
