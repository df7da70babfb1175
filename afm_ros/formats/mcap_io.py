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
``flush_interval`` seconds, so a SIGKILL loses at most that much. A file is *complete* only
when it ends with the footer and the closing magic, which are written by :meth:`SessionWriter.close`
alone and never after a failed write. :func:`read_session` reads complete and truncated files;
:func:`recover` rewrites a truncated file into a complete one.

Command line: ``python -m afm_ros.formats.mcap_io info FILE`` and ``python -m afm_ros.formats.mcap_io recover IN OUT``.
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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from mcap import __version__ as _MCAP_VERSION
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Header, Message, MessageIndex, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from afm_ros.core.physics.parameters import ParamSpec

MCAP_MAGIC = b"\x89MCAP0\r\n"
PROFILE = "ros2"
LIBRARY = f"afm_ros 0.1.0; mcap python {_MCAP_VERSION}"
DEFINITION_DELIMITER = "=" * 80
COMPRESSIONS = {"none": CompressionType.NONE, "lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD}
PARAMETER_METADATA_PREFIX = "afm_ros.parameters:"

# --- parameters of the recorder and replay nodes (ParamSpec, no ROS import) -----------------


def _specs(*specs: ParamSpec) -> dict[str, ParamSpec]:
    return {s.name: s for s in specs}


RECORDER_SPECS = _specs(
    ParamSpec("output", "", "", "output .mcap file; empty = afm_session_<YYYY_MM_DD-HH_MM_SS>.mcap "
              "in the current working directory", kind=str, live=False),
    ParamSpec("topics", "", "", "comma-separated topic names or glob patterns (relative names resolve "
              "in the recorder's namespace); empty = every topic, or under a namespace every topic of that "
              "namespace plus /diagnostics and /rosout (/parameter_events is always recorded)",
              kind=str, live=False),
    ParamSpec("exclude", "", "", "comma-separated topic names or glob patterns never recorded",
              kind=str, live=False),
    ParamSpec("compression", "zstd", "", "chunk compression", kind=str, live=False,
              choices=("none", "lz4", "zstd")),
    ParamSpec("chunk_size", 4 * 1024 * 1024, "B", "uncompressed size at which a chunk is closed",
              low=1024, high=1 << 30, kind=int, live=False),
    ParamSpec("flush_interval", 1.0, "s", "wall-clock period of closing the current chunk and handing "
              "it to the OS; bounds the data lost by a SIGKILL", low=0.05, high=60.0, live=False),
    ParamSpec("discovery_period", 0.5, "s", "wall-clock period of looking for new topics and nodes",
              low=0.05, high=60.0, live=False),
)

REPLAY_SPECS = _specs(
    ParamSpec("file", "", "", "the .mcap session to replay (required)", kind=str, live=False),
    ParamSpec("rate", 1.0, "1", "playback speed relative to the recording (2 = twice as fast)",
              low=0.0, high=1000.0, low_open=True),
    ParamSpec("loop", False, "", "start again at the end of the file", kind=bool, live=False),
    ParamSpec("topics", "", "", "comma-separated recorded topic names or glob patterns to replay; "
              "empty = all", kind=str, live=False),
    ParamSpec("exclude", "/rosout,/parameter_events", "", "comma-separated recorded topics or glob "
              "patterns not replayed", kind=str, live=False),
    ParamSpec("topic_prefix", "", "", "namespace put in front of every replayed topic except /clock, "
              "e.g. /replay (ROS remapping rules apply as well)", kind=str, live=False),
    ParamSpec("publish_clock", True, "", "publish /clock (simulated time): the recorded /clock, or the "
              "end time of each replayed deflection chunk if /clock was not recorded", kind=bool, live=False),
    ParamSpec("start_delay", 0.5, "s", "wall time between creating the publishers and the first message "
              "(lets subscribers connect)", low=0.0, high=60.0, live=False),
)


class RecordingError(RuntimeError):
    """The session file cannot be created or written (message names the path and the cause)."""


class SessionFileError(RuntimeError):
    """A session file is missing, not MCAP, unreadable or has an unknown schema (names the file)."""


# --- message definitions, type hashes, QoS ------------------------------------------------

_MSG_FIELD_TYPE = re.compile(r"(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+")
_PRIMITIVES = {"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
               "int32", "uint32", "int64", "uint64", "string"}


def _split_type(type_name: str) -> tuple[str, str, str]:
    parts = type_name.split("/")
    if len(parts) == 2:
        return parts[0], "msg", parts[1]
    if len(parts) == 3:
        return parts[0], parts[1], parts[2]
    raise ValueError(f"message type {type_name!r} is not of the form pkg/msg/Type")


def _share_dir(package: str) -> Path:
    from ament_index_python.packages import get_package_share_directory
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
                result += "\n" + DEFINITION_DELIMITER + "\nMSG: " + dep + "\n" + append(dep, depth - 1)
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
            f"  liveliness_lease_duration:\n{_duration_yaml(q.liveliness_lease_duration.nanoseconds, '  ')}"
            f"  avoid_ros_namespace_conventions: {'true' if q.avoid_ros_namespace_conventions else 'false'}")
    return "\n".join(out)


def default_output_path(now: _dt.datetime | None = None, directory: str | os.PathLike | None = None) -> Path:
    """``afm_session_YYYY_MM_DD-HH_MM_SS.mcap`` in ``directory`` (default: the current directory)."""
    now = now or _dt.datetime.now()
    return Path(directory or os.getcwd()) / now.strftime("afm_session_%Y_%m_%d-%H_%M_%S.mcap")


# --- writer ------------------------------------------------------------------------------


class SessionWriter:
    """Append-only rosbag2-layout MCAP writer with periodic flushing and fail-stop errors.

    Every OSError (full disk, I/O error) turns into :class:`RecordingError` naming the path; after
    the first failure nothing more is written, in particular never a footer, so a damaged file
    never claims to be complete.
    """

    def __init__(self, path: str | os.PathLike, compression: str = "zstd", chunk_size: int = 4 << 20):
        self.path = Path(path).absolute()
        if compression not in COMPRESSIONS:
            raise ValueError(f"compression={compression!r} is not allowed; allowed: {', '.join(COMPRESSIONS)}")
        parent = self.path.parent
        if not parent.is_dir():
            raise RecordingError(f"cannot record to {self.path}: directory {parent} does not exist "
                                 "or is not a directory")
        try:
            self._stream = open(self.path, "xb")  # never overwrite an existing session
        except FileExistsError:
            raise RecordingError(f"cannot record to {self.path}: the file already exists "
                                 "(choose another output path)") from None
        except OSError as exc:
            raise RecordingError(f"cannot record to {self.path}: {exc.strerror or exc}") from exc
        self.error: RecordingError | None = None
        self.closed = False
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.message_count = 0
        self.bytes_written = 0
        self._writer = Writer(self._stream, chunk_size=chunk_size, compression=COMPRESSIONS[compression])
        self._guard(lambda: (self._writer.start(profile=PROFILE, library=LIBRARY), self._stream.flush()))

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
            f"`python -m afm_ros.formats.mcap_io recover {self.path} OUT.mcap`)")
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

    def add_channel(self, topic: str, type_name: str, offered_qos_profiles: str = "",
                    topic_type_hash: str | None = None) -> int:
        """Register ``topic`` (schema created once per type) and return its channel id."""
        if topic in self._channels:
            return self._channels[topic]
        if type_name not in self._schemas:
            data = message_definition(type_name).encode()
            self._schemas[type_name] = self._guard(
                lambda: self._writer.register_schema(type_name, "ros2msg", data))
        metadata = {"offered_qos_profiles": offered_qos_profiles}
        h = type_hash(type_name) if topic_type_hash is None else topic_type_hash
        if h:
            metadata["topic_type_hash"] = h
        cid = self._guard(lambda: self._writer.register_channel(topic, "cdr", self._schemas[type_name], metadata))
        self._channels[topic] = cid
        return cid

    def write(self, channel_id: int, data: bytes, log_time: int, publish_time: int | None = None,
              sequence: int = 0) -> None:
        """Append one CDR message; times in ns (wall clock, see module doc)."""
        if self.error is not None or self.closed:
            self._guard(lambda: None)  # raises the stored error
        try:
            self._writer.add_message(channel_id, log_time, data,
                                     log_time if publish_time is None else publish_time, sequence)
        except OSError as exc:
            self._failed(exc)
        self.message_count += 1
        self.bytes_written += len(data)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._guard(lambda: self._writer.add_metadata(name, {str(k): str(v) for k, v in data.items()}))

    def flush(self) -> None:
        """Close the current chunk and hand everything to the OS (survives a process kill)."""
        self._guard(self._writer.flush)

    def close(self) -> None:
        """Write summary, index and footer (only if nothing failed) and close the file."""
        if self.closed:
            return
        self._guard(self._writer.finish)
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
    damaged: list = field(default_factory=list)  # (offset, length, reason) of every skipped region
    skipped_messages: int = 0  # messages in skipped chunks (from their message indexes, where intact)
    chunks: int = 0  # intact chunks read

    @property
    def damage_text(self) -> str:
        """One sentence on the damage met ('' if none)."""
        if not self.damaged:
            return ""
        size = sum(n for _, n, _ in self.damaged)
        first = self.damaged[0]
        return (f"{len(self.damaged)} damaged region(s) skipped ({size} bytes, first at byte {first[0]}: "
                f"{first[2]}); {self.skipped_messages} messages lost there, every intact chunk after it read")

    @property
    def topics(self) -> dict[str, str]:
        """topic -> type name."""
        return {c.topic: self.schemas[c.schema_id].name if c.schema_id in self.schemas else ""
                for c in self.channels.values()}


def check_mcap_file(path: str | os.PathLike) -> Path:
    """Raise SessionFileError unless ``path`` is a regular file that starts with the MCAP magic."""
    p = Path(path)
    if not p.exists():
        raise SessionFileError(f"session file {p} does not exist")
    if p.is_dir():
        raise SessionFileError(f"session file {p} is a directory, not an .mcap file")
    mode = p.stat().st_mode
    if not stat.S_ISREG(mode):
        kind = "a FIFO" if stat.S_ISFIFO(mode) else "a device" if (stat.S_ISCHR(mode) or stat.S_ISBLK(mode)) \
            else "a socket" if stat.S_ISSOCK(mode) else "not a regular file"
        raise SessionFileError(f"session file {p} is {kind}, not a regular .mcap file (it could block forever)")
    try:
        with open(p, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise SessionFileError(f"cannot read session file {p}: {exc.strerror}") from exc
    if head != MCAP_MAGIC:
        what = "empty" if not head else f"starts with {head[:8]!r}"
        raise SessionFileError(f"{p} is not an MCAP file ({what}; expected the MCAP magic {MCAP_MAGIC!r})")
    return p


_OPCODES = {o.value for o in Opcode}
_RECORD_CLASSES = {Opcode.HEADER: Header, Opcode.FOOTER: Footer, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel,
                   Opcode.CHUNK: Chunk, Opcode.MESSAGE_INDEX: MessageIndex, Opcode.METADATA: Metadata}
_RESYNC_WINDOW = 64 << 20  # how far past a damaged record header to look for the next record [B]


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


_RESYNC_OPCODES = frozenset((Opcode.CHUNK, Opcode.MESSAGE_INDEX, Opcode.DATA_END, Opcode.CHANNEL, Opcode.SCHEMA,
                             Opcode.METADATA, Opcode.MESSAGE))


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


def read_session(path: str | os.PathLike, scan: SessionScan | None = None,
                 topics: set[str] | None = None) -> Iterator[SessionMessage]:
    """Yield every readable message in file order (complete, truncated or damaged file).

    ``scan`` (optional) is filled while reading: schemas, channels, metadata, counts and, once the
    generator is exhausted, whether the file was complete, why reading stopped early, and every
    damaged region it skipped. Every chunk carries its own length and CRC: a chunk that fails them
    is skipped (its message index, if intact, says how many messages it held) and reading goes on
    with the next record; a damaged record header is skipped by finding the next plausible record.
    Raises SessionFileError for a missing, non-regular or non-MCAP file.
    """
    p = check_mcap_file(path)
    scan = scan if scan is not None else SessionScan(p)
    scan.path = p
    size = scan.file_size = p.stat().st_size
    saw_footer = False
    skipped_chunk_end = None  # end of the last skipped chunk: its message indexes follow it
    with open(p, "rb") as f:
        pos = len(MCAP_MAGIC)
        scan.bytes_read = pos
        while pos < size:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                if not (saw_footer or head == MCAP_MAGIC[:len(head)]):
                    scan.truncated_reason = f"file ends inside a record header at byte {pos} of {size}"
                break
            opcode, length = head[0], struct.unpack_from("<Q", head, 1)[0]
            end = pos + 9 + length
            if opcode not in _OPCODES or end > size:
                if opcode in _OPCODES and _resync(f, pos, size) is None:
                    scan.truncated_reason = (f"file ends inside a record: intact up to byte {pos} of {size} "
                                             f"(a {Opcode(opcode).name.lower()} record of {length} bytes)")
                    break
                nxt = _resync(f, pos, size)
                if nxt is None:
                    scan.damaged.append((pos, size - pos, f"unreadable record header (opcode {opcode:#04x})"))
                    scan.truncated_reason = f"damaged at byte {pos}: no intact record after it"
                    break
                scan.damaged.append((pos, nxt - pos, f"unreadable record header (opcode {opcode:#04x})"))
                pos = nxt
                continue
            f.seek(pos + 9)
            body = f.read(length)
            try:
                record = _parse(opcode, body)
                inner = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else None
            except Exception as exc:  # noqa: BLE001 - any parser error is damage of this record
                reason = f"{type(exc).__name__}: {exc}".strip(": ")
                scan.damaged.append((pos, end - pos, f"{'chunk' if opcode == Opcode.CHUNK else 'record'} "
                                     f"{reason[:200]}"))
                skipped_chunk_end = end if opcode == Opcode.CHUNK else None
                pos = end
                continue
            if inner is not None:
                scan.chunks += 1
                skipped_chunk_end = None
                records = inner
            elif isinstance(record, MessageIndex):
                if skipped_chunk_end is not None:  # the index of a skipped chunk: what was lost
                    scan.skipped_messages += len(record.records)
                records = []
            else:
                records = [record] if record is not None else []
            for rec in records:
                if isinstance(rec, Message):
                    ch = scan.channels.get(rec.channel_id)
                    if ch is None or (topics is not None and ch.topic not in topics):
                        continue
                    scan.message_counts[ch.topic] = scan.message_counts.get(ch.topic, 0) + 1
                    schema = scan.schemas.get(ch.schema_id)
                    yield SessionMessage(ch.topic, schema.name if schema else "", rec.data, rec.log_time,
                                         rec.publish_time, rec.sequence, rec.channel_id)
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
                break
    if not scan.truncated_reason and not saw_footer:
        scan.truncated_reason = "no footer (the recorder did not close the file)"
    if scan.damaged and not scan.truncated_reason:
        scan.truncated_reason = scan.damage_text
    elif scan.damaged:
        scan.truncated_reason += "; " + scan.damage_text
    scan.complete = saw_footer and not scan.damaged and scan.truncated_reason == ""


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
    from rclpy.serialization import deserialize_message, serialize_message
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
    from rclpy.serialization import deserialize_message
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


def recover(src: str | os.PathLike, dst: str | os.PathLike, compression: str | None = None) -> RecoverResult:
    """Copy every intact record of ``src`` (typically a killed recording) into a complete file ``dst``."""
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
                        lambda: out._writer.register_schema(schema.name, schema.encoding, schema.data))
                cid = out._guard(lambda: out._writer.register_channel(
                    ch.topic, ch.message_encoding, out._schemas[schema.name], dict(ch.metadata)))
                written_channels[m.channel_id] = cid
            out.write(cid, m.data, m.log_time, m.publish_time, m.sequence)
            count += 1
            last = max(last, m.log_time)
        for md in scan.metadata:
            out.add_metadata(md.name, md.metadata)
        out.add_metadata("afm_ros.recovered", {
            "source": str(src_path), "source_complete": str(scan.complete).lower(),
            "reason": scan.truncated_reason, "bytes_read": str(scan.bytes_read),
            "source_size": str(scan.file_size)})
        out.close()
    except BaseException:
        if not out.closed:
            out._abandon()
        raise
    return RecoverResult(src_path, out.path, count, scan.complete, scan.truncated_reason, scan.bytes_read,
                         scan.file_size, last)


def parameter_metadata(scan: SessionScan) -> dict[str, dict[str, str]]:
    """Initial parameter snapshots stored as metadata records: node -> {name: YAML value}."""
    out = {}
    for md in scan.metadata:
        if md.name.startswith(PARAMETER_METADATA_PREFIX):
            out[md.name[len(PARAMETER_METADATA_PREFIX):]] = dict(md.metadata)
    return out


# --- command line ------------------------------------------------------------------------


def _info(path: str) -> int:
    scan = scan_session(path)
    print(f"file: {scan.path} ({scan.file_size} bytes)")
    print(f"complete: {'yes' if scan.complete else 'no - ' + scan.truncated_reason}")
    if scan.header is not None:
        print(f"profile: {scan.header.profile}  library: {scan.header.library}")
    for topic, type_name in sorted(scan.topics.items()):
        print(f"  {topic:40s} {type_name:36s} {scan.message_counts.get(topic, 0):8d} msgs")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m afm_ros.formats.mcap_io",
                                     description="Inspect or recover afm_ros session files (.mcap).")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p_info = sub.add_parser("info", help="topics, message counts and completeness of a session file")
    p_info.add_argument("file")
    p_rec = sub.add_parser("recover", help="copy the intact part of a truncated session into a complete file")
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
    state = "was complete" if res.complete_input else f"was incomplete ({res.reason})"
    print(f"recovered {res.messages} messages from {res.input} ({state}; {res.bytes_read} of "
          f"{res.input_size} bytes intact) into {res.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
