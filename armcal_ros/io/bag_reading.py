"""
Reading rosbag2 bags, corrupt ones included, with every lost message counted.

:func:`iter_raw` yields :class:`RawMessage` records whose ``deserialize()`` a caller may wrap in
``try/except DeserializationError`` to skip a corrupt message and keep going;
:func:`iter_messages` does that for you when ``skip_errors=True``.  :func:`bag_topics` lists
topics, types and counts.  (:mod:`armcal_ros.io.bag` re-exports all three, with the writer.)

Corrupt bags: rosbag2 bags in mcap or sqlite3 storage are read by this module itself (rosbags'
readers stop at, or silently skip past, the first corrupt record).  An mcap file's data section is
walked record by record: a chunk that does not decompress or fails its CRC is skipped, a record
with an impossible opcode or length starts a search for the next chunk.  A sqlite3 file is read by
row-id range, halving a range that raises down to the rows that do.  Nothing is lost silently:
the messages each topic should have (metadata.yaml) minus those delivered are the losses,
returned in a :class:`BagLosses` with the reasons.  Only a bag whose metadata.yaml, storage file
header or sqlite3 schema is destroyed cannot be read (:class:`BagReadError`).  Checksums make the
delivered messages byte-exact: :class:`~armcal_ros.io.bag.BagWriter` writes each mcap chunk's CRC
(rosbags 0.11 writes none; ``ros2 bag record`` does) and a CRC per sqlite3 message
(:data:`CRC_TABLE`).  A bag without them is checked as far as its structure allows (message
index, record lengths).  Other bags (rosbag1, whole-file compression) go through rosbags'
AnyReader, which stops at the first corrupt record; the rest is counted as lost.
"""


from dataclasses import dataclass, field
import heapq
from operator import itemgetter
import os
from pathlib import Path, PurePath
import re
import sqlite3
import struct
from typing import Callable, Dict, List, Optional
from urllib.parse import quote
import warnings
import zlib

from lz4.frame import decompress as lz4_decompress
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_types_from_idl, get_types_from_msg, get_typestore, Stores
import yaml

try:
    from compression import zstd
except ImportError:             # Python < 3.14: rosbags depends on the backport
    from backports import zstd

STORAGES = ('mcap', 'sqlite3')
#: Table of per-message CRC-32s :class:`~armcal_ros.io.bag.BagWriter` adds to a sqlite3 bag
#: (rosbag2 and ``ros2 bag`` ignore tables they do not know).
CRC_TABLE = 'armcal_message_crc'


class DeserializationError(ValueError):
    """A message in a bag could not be deserialised (corrupt or truncated data)."""


def jazzy_typestore():
    """Return the rosbags typestore with the ROS 2 Jazzy message definitions."""
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass
class RawMessage:
    """One message as stored: call ``deserialize()`` to decode it (may raise)."""

    topic: str
    msgtype: str
    t_ns: int
    rawdata: bytes
    _decode: Callable

    def deserialize(self):
        """Decode the CDR bytes; raises :class:`DeserializationError` on corrupt data."""
        try:
            return self._decode(self.rawdata, self.msgtype)
        except Exception as err:  # rosbags raises several types on truncated CDR
            raise DeserializationError(
                f'{self.topic} at t={self.t_ns} ns: cannot deserialise {self.msgtype}: {err}'
            ) from err


class BagReadError(ValueError):
    """A bag cannot be read at all: its metadata.yaml, or its storage file's header or schema."""


class BagLossWarning(UserWarning):
    """Warned when a reading lost messages and its caller passed no :class:`BagLosses`."""


#: The most reasons a :class:`BagLosses` keeps (the rest are counted).
MAX_PROBLEMS = 50


@dataclass
class BagLosses:
    """
    What one reading of a bag delivered and what it lost, per topic.

    ``expected`` is the bag's own count of each topic read (metadata.yaml), ``delivered`` what
    the reading yielded and ``problems`` what it skipped and why (file and byte offset or row).
    Once ``complete`` (the reading reached the end of the bag) :attr:`lost` is exact.
    """

    expected: Dict[str, int] = field(default_factory=dict)
    delivered: Dict[str, int] = field(default_factory=dict)
    problems: List[str] = field(default_factory=list)
    more_problems: int = 0
    complete: bool = False

    def reset(self):
        """Forget an earlier reading."""
        self.expected, self.delivered, self.problems = {}, {}, []
        self.more_problems, self.complete = 0, False

    def note(self, problem):
        """Record why messages were skipped."""
        if len(self.problems) < MAX_PROBLEMS:
            self.problems.append(problem)
        else:
            self.more_problems += 1

    @property
    def lost(self):
        """Return {topic: messages the bag has that the reading did not deliver} (> 0 only)."""
        return {t: n - self.delivered.get(t, 0) for t, n in self.expected.items()
                if n > self.delivered.get(t, 0)}

    def reasons(self, limit=3):
        """Return the first ``limit`` problems in one line (and how many more there are)."""
        more = len(self.problems) + self.more_problems - limit
        why = '; '.join(self.problems[:limit]) + (f'; {more} more' if more > 0 else '')
        return why or 'reason unknown'

    def describe(self, limit=3):
        """Return one line: the lost counts per topic and the first ``limit`` reasons."""
        lost = self.lost
        counts = ', '.join(f'{t} {n} of {self.expected[t]}' for t, n in lost.items())
        return f'{sum(lost.values())} messages lost ({counts}): {self.reasons(limit)}'


def _message_crc(topic_id, t_ns, data):
    """Return the CRC-32 of a sqlite3 message row: its topic id, time stamp and data."""
    return zlib.crc32(data, zlib.crc32(struct.pack('<qq', topic_id, t_ns)))


class _Rosbag2:
    """A rosbag2 directory as its metadata.yaml describes it."""

    def __init__(self, path):
        self.path = path
        try:
            info = yaml.safe_load((path / 'metadata.yaml').read_text())
            info = info['rosbag2_bagfile_information']
            self.storage = str(info['storage_identifier'])
            self.files = [path / PurePath(str(x)).name for x in info['relative_file_paths']]
            mode = str(info.get('compression_mode') or '').lower()
            self.compression = '' if mode == 'none' else mode
            topics = [(str(x['topic_metadata']['name']), str(x['topic_metadata']['type']),
                       int(x['message_count'])) for x in info['topics_with_message_count']]
        except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError,
                ValueError) as exc:
            raise BagReadError(f'bag {path} is not readable: its metadata.yaml is not a rosbag2 '
                               f'bag description ({type(exc).__name__}: {exc})') from exc
        self.types, self.counts = {}, {}
        for name, msgtype, n in topics:
            self.types.setdefault(name, msgtype)
            self.counts[name] = self.counts.get(name, 0) + n

    def open_files(self, losses):
        """Open the storage files; one that is not readable is noted, all unreadable raise."""
        opener = {'mcap': _McapFile, 'sqlite3': _Sqlite3File}[self.storage]
        files, errors = [], []
        for path in self.files:
            try:
                files.append(opener(path, self))
            except BagReadError as exc:
                errors.append(exc)
                losses.note(str(exc))
        if errors and not files:
            raise errors[0] if len(errors) == 1 else BagReadError(
                f'bag {self.path} is not readable: ' + '; '.join(map(str, errors)))
        return files


def _rosbag2(path):
    """Return the :class:`_Rosbag2` this module reads itself, or None (rosbags reads it)."""
    if not (path.is_dir() and (path / 'metadata.yaml').is_file()):
        return None
    bag = _Rosbag2(path)
    if bag.storage not in STORAGES or bag.compression not in ('', 'message'):
        return None
    return bag


_MAGIC = b'\x89MCAP0\r\n'
_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK, _MESSAGE_INDEX = range(1, 8)
_DATA_END = 0x0F
_MAX_OPCODE = 0x10
_COMPRESSIONS = (b'', b'zstd', b'lz4')
_COMPRESSED_MAGIC = {b'zstd': b'\x28\xb5\x2f\xfd', b'lz4': b'\x04\x22\x4d\x18'}
_SCAN_BLOCK = 1 << 20          # bytes searched at a time for the next chunk after garbage
_MAX_CHUNK = 1 << 32           # a chunk claiming more is corrupt
_RUN_BYTES = 1 << 22           # top-level messages (an unchunked file) read at a time
#: Chunks are read from blocks this big: fewer system calls, and with glibc's malloc a big block
#: freed early keeps each chunk's buffers on the heap instead of freshly mapped pages (bags/demo:
#: 4724 chunks of 2 kB that decompress to 1.2 MB; 2.9 s with 8 MiB blocks, 1.9 s with 4 MiB).
_READ_AHEAD = 1 << 22
_CHUNK_HEAD = struct.Struct('<BQQQQII')
_MESSAGE_HEAD = struct.Struct('<HIQ')
_U64 = struct.Struct('<Q')


@dataclass
class _Span:
    """A chunk of an mcap file, or a run of its top-level message records."""

    offset: int                 # of the chunk record (or the first message record)
    data_offset: int
    size: int                   # bytes at data_offset
    start: int                  # log time range
    end: int
    compression: Optional[bytes] = None     # None: top-level records, as they are
    usize: int = 0
    crc: int = 0
    #: {record offset in the chunk: (channel, log time)} from its message index records.
    index: Optional[Dict] = None


def _string(buf, pos):
    """Return (bytes of the uint32-prefixed string at ``pos``, position after it)."""
    (n,) = struct.unpack_from('<I', buf, pos)
    end = pos + 4 + n
    if end > len(buf):
        raise ValueError('a string runs past its record')
    return bytes(buf[pos + 4:end]), end


def _decompress(data, compression, size):
    """Decompress a chunk's records (at most ``size`` + 1 bytes are produced)."""
    if compression == b'zstd':
        d = zstd.ZstdDecompressor()
        raw = d.decompress(data, size + 1)
        if not d.eof or d.unused_data:
            raise ValueError('the zstd frame does not end where the chunk does')
        return raw
    if compression == b'lz4':
        return lz4_decompress(data)
    return data


class _McapFile:
    """
    One mcap storage file, read as far as it is readable.

    The data section is walked record by record (the summary, when intact, only adds schemas and
    channels); a record whose opcode or length is impossible starts a search for the next chunk,
    and the bytes in between are noted as lost.
    """

    def __init__(self, path, bag):
        self.path, self.name, self.bag = path, path.name, bag
        self.channels, self.schemas, self.definitions = {}, {}, {}
        self.loose = False          # the file has top-level message records (no chunks)
        self._block, self._block_at = b'', 0
        try:
            self.f = open(path, 'rb')
        except OSError as exc:
            raise BagReadError(f'bag file {path} is not readable: {exc.strerror}') from exc
        try:
            self.size = os.fstat(self.f.fileno()).st_size
            self.data_start = self._header()
            self.data_end = self._footer()
        except BaseException:
            self.f.close()
            raise

    def close(self):
        """Close the file."""
        self.f.close()

    def _read(self, offset, n):
        self.f.seek(offset)
        return self.f.read(n)

    def _read_ahead(self, offset, n):
        """Return ``n`` bytes at ``offset``, from a block of :data:`_READ_AHEAD` bytes."""
        i = offset - self._block_at
        if i < 0 or i + n > len(self._block):
            if n >= _READ_AHEAD:
                return self._read(offset, n)
            self._block, self._block_at, i = b'', offset, 0
            self._block = self._read(offset, _READ_AHEAD)
        return self._block[i:i + n]

    def _header(self):
        """Check the magic and header record; return where the data section starts."""
        head = self._read(0, 17)
        if len(head) < 17 or head[:8] != _MAGIC or head[8] != _HEADER:
            raise BagReadError(f'bag file {self.path} is not readable: it does not start with an '
                               'mcap header (the file is cut short or its header destroyed)')
        (length,) = _U64.unpack_from(head, 9)
        if length > 1 << 20 or 17 + length > self.size:
            raise BagReadError(f'bag file {self.path} is not readable: its mcap header record '
                               f'claims {length} bytes')
        return 17 + length

    def _footer(self):
        """Read the footer and the summary's schemas and channels; return the data end."""
        if self.size < self.data_start + 37:
            return self.size
        tail = self._read(self.size - 37, 37)
        footer = self.size - 37
        if tail[-8:] != _MAGIC or tail[0] != _FOOTER or _U64.unpack_from(tail, 1)[0] != 20:
            return self.size                    # cut short or the footer destroyed: walk it all
        (summary,) = _U64.unpack_from(tail, 9)
        if not self.data_start + 13 <= summary <= footer:
            return footer
        data_end = self._read(summary - 13, 13)
        if data_end[0] != _DATA_END or _U64.unpack_from(data_end, 1)[0] != 4:
            return footer
        p = summary
        while p + 9 <= footer:
            head = self._read(p, 9)
            (length,) = _U64.unpack_from(head, 1)
            if p + 9 + length > footer:
                break
            if head[0] in (_SCHEMA, _CHANNEL):
                self._meta_record(head[0], self._read(p + 9, length))
            p += 9 + length
        return summary

    def _meta_record(self, op, body):
        """Take a schema or channel record; one that is corrupt or foreign is ignored."""
        try:
            (key,) = struct.unpack_from('<H', body)
            if op == _SCHEMA:
                name, pos = _string(body, 2)
                encoding, pos = _string(body, pos)
                text, _ = _string(body, pos)
                name = name.decode()
                self.schemas.setdefault(key, name)
                self.definitions.setdefault(name, (encoding.decode(), text.decode()))
                return
            (schema,) = struct.unpack_from('<H', body, 2)
            topic, pos = _string(body, 4)
            encoding, _ = _string(body, pos)
            topic = topic.decode()
        except (struct.error, ValueError):
            return
        msgtype = self.bag.types.get(topic)
        if (msgtype is None or encoding != b'cdr' or key in self.channels
                or self.schemas.get(schema, msgtype) != msgtype):
            return
        self.channels[key] = (topic, msgtype)

    def _chunk_at(self, buf, i, p, end):
        """Return the :class:`_Span` of a chunk record at ``buf[i]`` (file offset p), or None."""
        try:
            op, length, start, stop, usize, crc, n = _CHUNK_HEAD.unpack_from(buf, i)
            compression = bytes(buf[i + 41:i + 41 + n])
            (csize,) = _U64.unpack_from(buf, i + 41 + n)
        except struct.error:
            return None
        data = i + 49 + n
        if (op != _CHUNK or compression not in _COMPRESSIONS or length != 40 + n + csize
                or start > stop or p + 9 + length > end or usize > _MAX_CHUNK
                or (not compression and csize != usize)):
            return None
        magic = _COMPRESSED_MAGIC.get(compression)
        if magic and csize and buf[data:data + 4] != magic:
            return None
        return _Span(p, p + 49 + n, csize, start, stop, compression, usize, crc)

    def _message_at(self, buf, i, p, end):
        """Tell whether a top-level message record is plausible at ``buf[i]`` (file offset p)."""
        try:
            (length,) = _U64.unpack_from(buf, i + 1)
            channel, _, t = _MESSAGE_HEAD.unpack_from(buf, i + 9)
        except struct.error:
            return False
        if buf[i] != _MESSAGE or length < 22 or p + 9 + length > end:
            return False
        if channel not in self.channels:
            return False
        after = self._read(p + 9 + length, 9)
        return len(after) < 9 or (0 < after[0] <= _MAX_OPCODE and p + 18 + length
                                  + _U64.unpack_from(after, 1)[0] <= self.size)

    def _resync(self, start, p, end, losses, why):
        """
        Return the offset of the next chunk (or top-level message) after ``start``; note the gap.

        ``p`` is where the impossible record is; ``start`` the record before it, whose length
        may be what is corrupt (then chunks between the two are found again).
        """
        pattern = re.compile(b'[\x05\x06]' if self.loose else b'\x06')
        pos, found = start + 1, end
        while pos < end and found == end:
            block = self._read(pos, _SCAN_BLOCK + 128)
            for m in pattern.finditer(block, 0, min(_SCAN_BLOCK, end - pos)):
                i = m.start()
                if (self._chunk_at(block, i, pos + i, end) is not None
                        or (self.loose and self._message_at(block, i, pos + i, end))):
                    found = pos + i
                    break
            pos += _SCAN_BLOCK
        where = f'the next chunk at byte {found}' if found < end else 'the end of the data'
        gap = f'bytes {p}-{found}' if found > p else f'the record at byte {start}'
        losses.note(f'{self.name}: {gap} not readable mcap records ({why}); skipped to {where}')
        return found

    def _walk(self, losses):
        """Return the file's chunks and runs of top-level messages, skipping corrupt bytes."""
        spans, last, run = [], None, None
        p, prev, end = self.data_start, self.data_start - 1, self.data_end
        while p < end:
            head = self._read(p, 70)
            if len(head) < 9:
                losses.note(f'{self.name}: the file ends inside a record at byte {p}')
                break
            op, (length,) = head[0], _U64.unpack_from(head, 1)
            if op == _FOOTER and length == 20:
                break
            if not 0 < op <= _MAX_OPCODE or p + 9 + length > end or (
                    op == _MESSAGE and length < 22):
                why = (f'opcode {op:#04x}' if not 0 < op <= _MAX_OPCODE else
                       f'a record of {length} bytes at byte {p}')
                p = prev = self._resync(prev, p, end, losses, why)
                last = run = None
                continue
            if op == _CHUNK:
                last, run = self._chunk_at(head, 0, p, end), None
                if last is None:
                    p = prev = self._resync(p, p, end, losses, 'a chunk with an impossible header')
                    continue
                spans.append(last)
            elif op == _MESSAGE_INDEX and last is not None:
                self._message_index(last, p, length)
            elif op == _MESSAGE:
                self.loose, last = True, None
                channel, _, t = _MESSAGE_HEAD.unpack_from(head, 9)
                if run is None or run.data_offset + run.size != p or run.size > _RUN_BYTES:
                    run = _Span(p, p, 0, t, t)
                    spans.append(run)
                run.size = p + 9 + length - run.data_offset
                run.start, run.end = min(run.start, t), max(run.end, t)
            elif op in (_SCHEMA, _CHANNEL) and length < 1 << 24:
                self._meta_record(op, self._read(p + 9, length))
                last = run = None
            else:
                last = run = None
            prev, p = p, p + 9 + length
        return spans

    def _message_index(self, span, p, length):
        """Add a message index record (channel, [(log time, offset)]) to its chunk."""
        if length > 1 << 28:
            return
        body = self._read(p + 9, length)
        try:
            channel, n = struct.unpack_from('<HI', body)
        except struct.error:
            return
        if n != len(body) - 6 or n % 16:
            return
        if span.index is None:
            span.index = {}
        for t, offset in struct.iter_unpack('<QQ', body[6:]):
            span.index[offset] = (channel, t)

    def _load(self, span, losses):
        """Return a span's records, checked as far as the file allows, or None (noted)."""
        data = self._read_ahead(span.data_offset, span.size)
        where = f'{self.name}: chunk at byte {span.offset}'
        if span.index is not None:
            where += f' ({len(span.index)} messages)'
        if len(data) != span.size:
            losses.note(f'{where}: the file ends inside it')
            return None
        if span.compression is None:
            return data
        try:
            raw = _decompress(data, span.compression, span.usize)
        except Exception as exc:    # zstd and lz4 raise their own errors on corrupt data
            losses.note(f'{where}: cannot decompress {span.compression.decode()}: {exc}')
            return None
        if len(raw) != span.usize:
            losses.note(f'{where}: {len(raw)} bytes, its header says {span.usize}')
            return None
        if span.crc and zlib.crc32(raw) != span.crc:
            losses.note(f'{where}: checksum mismatch')
            return None
        return raw

    def _records(self, span, raw, seq, wanted, losses):
        """
        Return [(log time, seq, k, topic, msgtype, data)] of a span's wanted messages.

        A chunk without a checksum is checked as far as its records allow: each message must be
        where its message index says, within the chunk's time range, and the message before a
        record that does not parse is dropped (its tail may be what broke the next one).
        """
        trusted = span.compression is not None and span.crc
        index = None if trusted else span.index
        channels, out, pos, n, k = self.channels, [], 0, len(raw), 0
        unknown, mismatched, appended, broken = 0, 0, False, None
        while pos < n:
            op = raw[pos]
            if pos + 9 > n or not 0 < op <= _MAX_OPCODE:
                broken = f'opcode {op:#04x} at {pos}'
                break
            (length,) = _U64.unpack_from(raw, pos + 1)
            end = pos + 9 + length
            if end > n or (op == _MESSAGE and length < 22):
                broken = f'a record of {length} bytes at {pos}'
                break
            appended = False
            if op == _MESSAGE:
                channel, _, t = _MESSAGE_HEAD.unpack_from(raw, pos + 9)
                if not trusted and ((index is not None and index.get(pos) != (channel, t))
                                    or not span.start <= t <= span.end):
                    mismatched += 1
                elif channel not in channels:
                    unknown += 1
                elif channels[channel][0] in wanted:
                    topic, msgtype = channels[channel]
                    out.append((t, seq, k, topic, msgtype, raw[pos + 31:end]))
                    appended = True
                k += 1
            elif op in (_SCHEMA, _CHANNEL):
                self._meta_record(op, raw[pos + 9:end])
            pos = end
        where = f'{self.name}: chunk at byte {span.offset}'
        if broken is not None:
            if appended and not trusted:
                out.pop()
            losses.note(f'{where}: records do not parse from {broken} on; the rest of it is lost')
        if mismatched:
            losses.note(f'{where}: {mismatched} message records disagree with its index')
        if unknown:
            losses.note(f'{where}: {unknown} messages on channels whose record is lost')
        out.sort()
        return out

    def messages(self, wanted, losses):
        """Yield (log time, topic, msgtype, data) of the wanted topics in log-time order."""
        spans = self._walk(losses)

        def source(seq, span):
            yield (span.start, seq, -1, None, None, None)
            if span.index:
                channels = {c for c, _ in span.index.values()}
                if (channels <= set(self.channels)
                        and not any(self.channels[c][0] in wanted for c in channels)):
                    return
            raw = self._load(span, losses)
            if raw is not None:
                out, raw = self._records(span, raw, seq, wanted, losses), None
                yield from out

        for t, _, k, topic, msgtype, data in heapq.merge(*(source(seq, span)
                                                           for seq, span in enumerate(spans))):
            if k >= 0:
                yield t, topic, msgtype, data


class _Sqlite3File:
    """
    One sqlite3 storage file, read as far as it is readable.

    Rows are read by id range; a range that raises is halved down to the single rows that do,
    which are noted as lost.  A bag written by :class:`BagWriter` has a CRC-32 per message
    (:data:`CRC_TABLE`): a row that does not match its checksum is not delivered.
    """

    def __init__(self, path, bag):
        self.path, self.name, self.bag = path, path.name, bag
        self.definitions = {}
        try:
            if not path.is_file():
                raise sqlite3.OperationalError('no such file')
            self.db = sqlite3.connect(f'file:{quote(str(path))}?mode=ro&immutable=1', uri=True)
        except sqlite3.Error as exc:
            raise BagReadError(f'bag file {path} is not readable: {exc}') from exc
        try:
            self.db.execute('PRAGMA cell_size_check = ON')
            # a file cut short is "malformed" as a whole unless the schema may be "written"
            # (the connection is read-only): then only the pages it lost fail
            self.db.execute('PRAGMA writable_schema = ON')
            tables = {name for (name,) in self.db.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")}
            missing = sorted({'messages', 'topics'} - tables)
            if missing:
                raise BagReadError(f'bag file {path} is not readable: it has no '
                                   f'{" or ".join(missing)} table')
            self.channels = {}
            for key, topic, msgtype in self.db.execute('SELECT id, name, type FROM topics'):
                if self.bag.types.get(topic) == msgtype:
                    self.channels[key] = (topic, msgtype)
        except sqlite3.Error as exc:
            self.db.close()
            raise BagReadError(f'bag file {path} is not readable: {exc}') from exc
        except BaseException:
            self.db.close()
            raise
        self.checked = CRC_TABLE in tables
        try:
            for name, encoding, text in self.db.execute(
                    'SELECT topic_type, encoding, encoded_message_definition '
                    'FROM message_definitions'):
                self.definitions.setdefault(name, (encoding, text))
        except sqlite3.Error:
            pass

    def close(self):
        """Close the database."""
        self.db.close()

    def _by_range(self, sql, lo, hi, losses, what):
        """Return the rows of ``sql`` (ids in [?, ?)) over [lo, hi), halving failing ranges."""
        rows, bad, todo = [], [], [(lo, hi)]
        while todo:
            a, b = todo.pop()
            try:
                rows += self.db.execute(sql, (a, b)).fetchall()
            except (sqlite3.Error, MemoryError) as exc:
                if b - a > 1:
                    m = (a + b) // 2
                    todo += [(m, b), (a, m)]
                elif bad and bad[-1][1] == a:
                    bad[-1][1] = b
                else:
                    bad.append([a, b, exc])
        for a, b, exc in bad:
            losses.note(f'{self.name}: {what} {a}-{b - 1} are not readable: {exc}')
        return rows, [(a, b) for a, b, _ in bad]

    def _by_id(self, ids, losses):
        """Return {id: (topic id, time, data)} of the rows ``ids``, halving failing lists."""
        out, todo = {}, [ids]
        while todo:
            part = todo.pop()
            try:
                out.update((i, (c, t, d)) for i, c, t, d in self.db.execute(
                    'SELECT id, topic_id, timestamp, data FROM messages WHERE id IN '
                    f'({",".join("?" * len(part))})', part))
            except (sqlite3.Error, MemoryError) as exc:
                if len(part) > 1:
                    todo += [part[len(part) // 2:], part[:len(part) // 2]]
                else:
                    losses.note(f'{self.name}: the data of message row {part[0]} is not '
                                f'readable: {exc}')
        return out

    def messages(self, wanted, losses):
        """Yield (time, topic, msgtype, data) of the wanted topics in time order."""
        keys = {key for key, (topic, _) in self.channels.items() if topic in wanted}
        try:
            (top,) = self.db.execute('SELECT max(id) FROM messages').fetchone()
        except sqlite3.Error:
            top = None
        top = top if isinstance(top, int) else 0
        hi = max(top, sum(self.bag.counts.values()))
        rows, unreadable = self._by_range('SELECT id, topic_id, timestamp, length(data) FROM '
                                          'messages WHERE id >= ? AND id < ?', 1, hi + 1, losses,
                                          'message rows')
        found, corrupt = {}, 0
        for i, c, t, n in rows:
            if c in self.channels and isinstance(t, int) and isinstance(n, int):
                found.setdefault(i, (c, t, n))
            else:
                corrupt += 1
        if corrupt:
            losses.note(f'{self.name}: {corrupt} message rows have an impossible topic, time '
                        'stamp or data')
        _note_missing_ids(losses, self.name, found, unreadable, max(top, max(found, default=0)))
        crcs = {}
        if self.checked:
            crcs = dict(r for r in self._by_range(
                f'SELECT id, crc FROM {CRC_TABLE} WHERE id >= ? AND id < ?', 1, hi + 1, losses,
                'checksum rows')[0] if len(r) == 2)
        order = sorted(((t, i), (c, n)) for i, (c, t, n) in found.items() if c in keys)
        bad, batch, size = 0, [], 0
        for k, ((t, i), (c, n)) in enumerate(order):
            batch.append((t, i, c))
            size += n
            if size < 1 << 23 and len(batch) < 256 and k + 1 < len(order):
                continue
            got = self._by_id([i for _, i, _ in batch], losses)
            for t, i, c in batch:
                row = got.get(i)
                if row is None:
                    bad += 1
                    continue
                data = row[2]
                if (row[:2] != (c, t) or not isinstance(data, bytes)
                        or (self.checked and crcs.get(i) != _message_crc(c, t, data))):
                    bad += 1
                    continue
                yield t, self.channels[c][0], self.channels[c][1], data
            batch, size = [], 0
        if bad:
            losses.note(f'{self.name}: {bad} message rows fail their checksum or changed')


def _note_missing_ids(losses, name, found, unreadable, top):
    """Note the message row ids up to ``top`` neither found nor noted as unreadable."""
    known = set(found)
    for a, b in unreadable:
        known.update(range(a, min(b, top + 1)))
    gaps, start = [], None
    for i in range(1, top + 2):
        if i <= top and i not in known:
            start = i if start is None else start
        elif start is not None:
            gaps.append(f'{start}-{i - 1}' if i - 1 > start else str(start))
            start = None
    if gaps:
        shown = ', '.join(gaps[:5]) + (f' and {len(gaps) - 5} more' if len(gaps) > 5 else '')
        losses.note(f'{name}: message row ids {shown} are missing (a corrupt page)')


def _register(typestore, msgtype, files, tried):
    """Add ``msgtype`` (not a Jazzy type) to ``typestore`` from a storage file's definition."""
    tried.add(msgtype)
    for f in files:
        encoding, text = f.definitions.get(msgtype, ('', ''))
        try:
            if encoding == 'ros2msg':
                types = get_types_from_msg(text, msgtype)
            elif encoding == 'ros2idl':
                types = {}
                for idl in text.split('=' * 80 + '\n'):
                    idl = idl.split('\n', 1)[1] if idl.startswith('IDL: ') else idl
                    if idl.strip():
                        types.update(get_types_from_idl(idl))
            else:
                continue
            typestore.register({k: v for k, v in types.items() if k not in typestore.fielddefs})
            return
        except Exception:           # a definition rosbags cannot parse: try the next file
            continue


def _read_rosbag2(bag, topics, losses):
    """Yield a rosbag2 bag's :class:`RawMessage` records, accounting in ``losses``."""
    wanted = set(bag.counts) if topics is None else set(topics) & set(bag.counts)
    losses.expected = {t: n for t, n in bag.counts.items() if t in wanted}
    if not wanted:
        return
    files = bag.open_files(losses)
    try:
        typestore, tried, delivered = jazzy_typestore(), set(), losses.delivered
        streams = [f.messages(wanted, losses) for f in files]
        merged = streams[0] if len(streams) == 1 else heapq.merge(*streams, key=itemgetter(0))
        for t, topic, msgtype, data in merged:
            if bag.compression == 'message':
                try:
                    data = zstd.decompress(data)
                except Exception as exc:    # zstd's own error types
                    losses.note(f'{topic} at t={t} ns: cannot decompress its zstd data: {exc}')
                    continue
            if msgtype not in typestore.fielddefs and msgtype not in tried:
                _register(typestore, msgtype, files, tried)
            delivered[topic] = delivered.get(topic, 0) + 1
            yield RawMessage(topic, msgtype, t, data, typestore.deserialize_cdr)
    finally:
        for f in files:
            f.close()


def _read_other(path, topics, losses):
    """Yield the messages of a bag rosbags reads (rosbag1, file-compressed rosbag2)."""
    try:
        reader = AnyReader([path], default_typestore=jazzy_typestore())
        reader.open()
    except FileNotFoundError:
        raise
    except Exception as exc:        # rosbags' reader errors, and what corrupt data raises
        raise BagReadError(f'bag {path} is not readable: {exc}') from exc
    try:
        conns = reader.connections
        if topics is not None:
            wanted = set(topics)
            conns = [c for c in conns if c.topic in wanted]
        for c in conns:
            losses.expected[c.topic] = losses.expected.get(c.topic, 0) + int(c.msgcount)
        if not conns:
            return
        delivered = losses.delivered
        try:
            for conn, t_ns, raw in reader.messages(connections=conns):
                delivered[conn.topic] = delivered.get(conn.topic, 0) + 1
                yield RawMessage(conn.topic, conn.msgtype, t_ns, raw,
                                 reader.typestore.deserialize_cdr)
        except Exception as exc:    # rosbags stops at the first corrupt record
            losses.note(f'{path}: reading stopped at a corrupt record: {exc}')
    finally:
        reader.close()


def iter_raw(path, topics=None, losses=None):
    """
    Yield :class:`RawMessage` for every message (in bag-time order), optionally by topic.

    Corrupt data is skipped and reading goes on at the next readable chunk or row; what was lost
    is accounted in ``losses`` (a :class:`BagLosses`, reset first) - or, without one, warned as
    a :class:`BagLossWarning` at the end.  A bag that cannot be read at all (its metadata.yaml,
    or its storage file's header or schema destroyed) raises :class:`BagReadError`.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f'bag {path} does not exist')
    account = BagLosses() if losses is None else losses
    account.reset()
    bag = _rosbag2(path)
    yield from (_read_other(path, topics, account) if bag is None else
                _read_rosbag2(bag, topics, account))
    account.complete = True
    if losses is None and account.lost:
        warnings.warn(BagLossWarning(f'bag {path}: {account.describe()}'), stacklevel=2)


def iter_messages(path, topics=None, skip_errors=False, on_error=None, losses=None):
    """
    Yield (topic, msgtype, t_ns, msg) with ``msg`` a rosbags message dataclass.

    With ``skip_errors`` a message that fails to deserialise is skipped (``on_error`` is then
    called with the :class:`DeserializationError`, if given); otherwise the error propagates.
    ``losses`` is as for :func:`iter_raw` (it counts what the storage lost, not these).
    """
    for raw in iter_raw(path, topics, losses):
        try:
            msg = raw.deserialize()
        except DeserializationError as err:
            if not skip_errors:
                raise
            if on_error is not None:
                on_error(err)
            continue
        yield raw.topic, raw.msgtype, raw.t_ns, msg


def bag_topics(path):
    """
    Return {topic: (msgtype, message count)} of a bag, the counts as the bag records them.

    Raises :class:`BagReadError` when the bag cannot be read at all (as :func:`iter_raw`).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f'bag {path} does not exist')
    bag = _rosbag2(path)
    if bag is None:
        try:
            with AnyReader([path], default_typestore=jazzy_typestore()) as reader:
                return {name: (info.msgtype, int(info.msgcount))
                        for name, info in reader.topics.items()}
        except FileNotFoundError:
            raise
        except Exception as exc:    # rosbags' reader errors, and what corrupt data raises
            raise BagReadError(f'bag {path} is not readable: {exc}') from exc
    for f in bag.open_files(BagLosses()):
        f.close()
    return {t: (bag.types[t], n) for t, n in bag.counts.items()}
