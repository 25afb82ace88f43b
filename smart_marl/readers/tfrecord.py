"""TFRecord framing: the container of WOMD scenario shards (plain or GZIP-compressed as a whole).

Stage: the bottom of the WOMD reader (``smart_marl.readers.womd``); it hands on raw record payloads
(serialized protobuf messages) one at a time and knows nothing of what they contain.

A record is ``uint64 length (little-endian) | uint32 masked CRC32C(length bytes) | payload |
uint32 masked CRC32C(payload)``, masked CRC = ``((crc >> 15) | (crc << 17)) + 0xa282ead8 mod 2**32``.
Both CRCs are checked on reading; a bad or truncated record raises
:class:`~smart_marl.errors.ScenarioReadError` naming the file and the record index. A record's
declared length is checked before its payload is read: against what the file can still hold (the
bytes left in a plain file; :data:`GZIP_MAX_RATIO` times the compressed bytes of a GZIP file) and
against :data:`MAX_RECORD_BYTES`, so a few bytes declaring a huge record allocate nothing.

CRC32C (Castagnoli) uses the C-accelerated ``crc32c`` package when it is installed (GB/s) and a
table-driven numpy implementation otherwise (about 100 MB/s: the buffer is cut into many lanes that
advance one byte per numpy step, and the lane CRCs are then combined with the CRC's linearity).
"""

from __future__ import annotations

import gzip
import os
import struct
from typing import BinaryIO, Iterable, Iterator

import numpy as np

from ..errors import ScenarioReadError, check_regular_file

GZIP_MAGIC = b"\x1f\x8b"
MAX_RECORD_BYTES = 1 << 28
"""Largest record read by default (256 MiB; WOMD scenario records are a few MB)."""
GZIP_MAX_RATIO = 1032
"""DEFLATE expands at most about 1032:1, so a GZIP file of n bytes holds at most 1032 n bytes."""
_MASK_DELTA = 0xA282EAD8
_POLY_REFLECTED = 0x82F63B78  # CRC32C (Castagnoli), bit-reversed


# ---------------------------------------------------------------------------------------- CRC32C
def _make_table() -> np.ndarray:
    table = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        table = np.where(table & 1, (table >> np.uint32(1)) ^ np.uint32(_POLY_REFLECTED), table >> np.uint32(1))
    return table.astype(np.uint32)


_TABLE = _make_table()
_TABLE_LIST = [int(v) for v in _TABLE]


def _raw_update_py(crc: int, data) -> int:
    """The raw (unreflected-init, no final xor) register update, one byte at a time."""
    table = _TABLE_LIST
    for b in data:
        crc = table[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc


# The register after n zero bytes is a linear map of the register: a 32x32 GF(2) matrix, kept as the
# images of the 32 basis bits (a list of ints) and applied through four 256-entry byte tables.
def _apply(matrix: list[int], vec: int) -> int:
    out, i = 0, 0
    while vec:
        if vec & 1:
            out ^= matrix[i]
        vec >>= 1
        i += 1
    return out


def _compose(outer: list[int], inner: list[int]) -> list[int]:
    return [_apply(outer, col) for col in inner]


_ONE_ZERO_BYTE = [_raw_update_py(1 << i, b"\x00") for i in range(32)]
_SHIFT_CACHE: dict[int, tuple[np.ndarray, ...]] = {}


def _shift_tables(num_bytes: int) -> tuple[np.ndarray, ...]:
    """Four byte tables T0..T3 with register-after-``num_bytes``-zeros(x) = xor of Tk[byte k of x]."""
    if num_bytes in _SHIFT_CACHE:
        return _SHIFT_CACHE[num_bytes]
    result = [1 << i for i in range(32)]  # identity
    power = _ONE_ZERO_BYTE
    n = num_bytes
    while n:
        if n & 1:
            result = _compose(power, result)
        power = _compose(power, power)
        n >>= 1
    tables = []
    for k in range(4):
        t = np.zeros(256, dtype=np.uint32)
        for bit in range(8):
            idx = np.arange(256)
            t ^= np.where(idx >> bit & 1, np.uint32(result[8 * k + bit]), np.uint32(0)).astype(np.uint32)
        tables.append(t)
    if len(_SHIFT_CACHE) < 64:
        _SHIFT_CACHE[num_bytes] = tuple(tables)
    return tuple(tables)


def _shift(crc: int, tables) -> int:
    t0, t1, t2, t3 = tables
    return int(t0[crc & 0xFF] ^ t1[(crc >> 8) & 0xFF] ^ t2[(crc >> 16) & 0xFF] ^ t3[crc >> 24])


def crc32c_numpy(data: bytes | bytearray | memoryview) -> int:
    """CRC32C of ``data`` without any C extension (numpy, lanes advanced in parallel)."""
    buf = np.frombuffer(memoryview(data).cast("B"), dtype=np.uint8)
    n = len(buf)
    if n < 2048:
        raw = _raw_update_py(0xFFFFFFFF, buf.tobytes())
        return raw ^ 0xFFFFFFFF
    lanes = 1 << max(6, min(12, (n.bit_length() // 2)))  # about sqrt(n) lanes
    lane_len = n // lanes
    block = buf[: lanes * lane_len].reshape(lanes, lane_len)
    regs = np.zeros(lanes, dtype=np.uint32)
    table = _TABLE
    eight = np.uint32(8)
    for j in range(lane_len):  # every lane starts from a zero register
        regs = table[(regs ^ block[:, j]) & np.uint32(0xFF)] ^ (regs >> eight)
    shift = _shift_tables(lane_len)
    acc = _shift(0xFFFFFFFF, shift)  # the initial register, carried through the first lane
    acc ^= int(regs[0])
    for r in regs[1:].tolist():
        acc = _shift(acc, shift) ^ r
    acc = _raw_update_py(acc, buf[lanes * lane_len :].tobytes())
    return acc ^ 0xFFFFFFFF


try:  # C-accelerated CRC32C when available (the optional ``womd`` extra installs ``crc32c``)
    from crc32c import crc32c as _crc32c_c  # type: ignore

    def _crc32c_fast(data) -> int:
        return _crc32c_c(data)

    CRC32C_IMPLEMENTATION = "crc32c"
except ImportError:  # pragma: no cover - depends on the environment
    try:
        import google_crc32c as _google_crc32c  # type: ignore

        def _crc32c_fast(data) -> int:
            return _google_crc32c.value(bytes(data))

        CRC32C_IMPLEMENTATION = "google-crc32c"
    except ImportError:
        _crc32c_fast = None
        CRC32C_IMPLEMENTATION = "numpy"


def crc32c(data: bytes | bytearray | memoryview) -> int:
    """CRC32C (Castagnoli) of ``data``; ``crc32c(b"123456789") == 0xE3069283``."""
    if _crc32c_fast is not None:
        return _crc32c_fast(data)
    return crc32c_numpy(data)


def masked_crc32c(data: bytes | bytearray | memoryview) -> int:
    """The TFRecord form of the CRC: rotated right by 15 bits plus a constant."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


# --------------------------------------------------------------------------------------- reading
def is_gzip(head: bytes) -> bool:
    return head[:2] == GZIP_MAGIC


def _open(path: str) -> BinaryIO:
    check_regular_file(path)
    try:
        raw = open(path, "rb")
    except OSError as exc:
        raise ScenarioReadError(path, f"cannot open: {exc.strerror or exc}") from exc
    head = raw.read(2)
    raw.seek(0)
    if is_gzip(head):
        return gzip.GzipFile(fileobj=raw, mode="rb")  # closing it does not close raw; see _close
    return raw


def _read_exact(stream: BinaryIO, n: int) -> bytes:
    chunks, need = [], n
    while need:
        chunk = stream.read(need)
        if not chunk:
            break
        chunks.append(chunk)
        need -= len(chunk)
    return b"".join(chunks) if len(chunks) != 1 else chunks[0]


def header_looks_like_tfrecord(head: bytes) -> bool:
    """True when ``head`` starts with a 12-byte TFRecord header whose length CRC checks."""
    if len(head) < 12:
        return False
    (length_crc,) = struct.unpack("<I", head[8:12])
    return masked_crc32c(head[:8]) == length_crc


def _capacity(stream: BinaryIO) -> tuple[int, bool]:
    """(the most bytes the file can still hold, whether that bound is exact): the bytes left in a
    plain file, or GZIP_MAX_RATIO times the size of a compressed one."""
    inner = getattr(stream, "fileobj", None)
    raw = inner if inner is not None else stream
    size = os.fstat(raw.fileno()).st_size
    if inner is not None:
        return GZIP_MAX_RATIO * size, False
    return size - stream.tell(), True


def iter_records(path: str | os.PathLike, check_crc: bool = True, max_record_bytes: int = MAX_RECORD_BYTES) -> Iterator[bytes]:
    """Yield the payload of every record of a TFRecord file (plain or GZIP), one at a time.

    Raises ScenarioReadError(path, problem, record=i) on a truncated record, a CRC mismatch (the
    length CRC or the data CRC, named in the problem) or a declared length the file cannot hold or
    above ``max_record_bytes``.
    """
    path = os.fspath(path)
    stream = _open(path)
    try:
        index = 0
        while True:
            try:
                header = _read_exact(stream, 12)
            except (OSError, EOFError, gzip.BadGzipFile) as exc:
                raise ScenarioReadError(path, f"cannot read the record header: {exc}", record=index) from exc
            if not header:
                return
            if len(header) < 12:
                raise ScenarioReadError(
                    path, f"truncated record: the 12-byte header has only {len(header)} bytes", record=index
                )
            length, length_crc = struct.unpack("<QI", header)
            if check_crc and masked_crc32c(header[:8]) != length_crc:
                raise ScenarioReadError(path, "length CRC mismatch (corrupt header or not a TFRecord file)", record=index)
            if length > max_record_bytes:
                raise ScenarioReadError(path, f"record length {length} bytes is implausible (more than {max_record_bytes})",
                                        record=index)
            capacity, exact = _capacity(stream)
            if length + 4 > capacity:
                what = (f"only {capacity} bytes are left in the file" if exact
                        else f"a GZIP file of {capacity // GZIP_MAX_RATIO} bytes cannot hold that much")
                raise ScenarioReadError(path, f"truncated record: it declares {length} payload bytes but {what}", record=index)
            try:
                body = _read_exact(stream, length + 4)
            except (OSError, EOFError, gzip.BadGzipFile) as exc:
                raise ScenarioReadError(path, f"cannot read the record payload: {exc}", record=index) from exc
            if len(body) < length + 4:
                raise ScenarioReadError(
                    path, f"truncated record: expected {length} payload bytes plus a 4-byte CRC, got {len(body)} bytes",
                    record=index,
                )
            payload = memoryview(body)[:length]
            if check_crc:
                (data_crc,) = struct.unpack("<I", body[length:])
                if masked_crc32c(payload) != data_crc:
                    raise ScenarioReadError(path, "data CRC mismatch (the payload is corrupt)", record=index)
            yield body[:length]
            index += 1
    finally:
        inner = getattr(stream, "fileobj", None)
        stream.close()
        if inner is not None:
            inner.close()


# --------------------------------------------------------------------------------------- writing
def frame_record(payload: bytes) -> bytes:
    """One record with its length, its payload and both masked CRCs."""
    length = struct.pack("<Q", len(payload))
    return b"".join((length, struct.pack("<I", masked_crc32c(length)), payload, struct.pack("<I", masked_crc32c(payload))))


class TFRecordWriter:
    """Write records to a TFRecord file, plain or GZIP-compressed (``compress=True``)."""

    def __init__(self, path: str | os.PathLike, compress: bool = False):
        self.path = os.fspath(path)
        self._raw = open(self.path, "wb")
        self._stream: BinaryIO = gzip.GzipFile(fileobj=self._raw, mode="wb", mtime=0) if compress else self._raw
        self.num_records = 0

    def write(self, payload: bytes) -> None:
        self._stream.write(frame_record(payload))
        self.num_records += 1

    def close(self) -> None:
        if self._stream is not self._raw:
            self._stream.close()
        self._raw.close()

    def __enter__(self) -> "TFRecordWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_records(payloads: Iterable[bytes], path: str | os.PathLike, compress: bool = False) -> int:
    """Write every payload as one record; returns the number of records."""
    with TFRecordWriter(path, compress=compress) as writer:
        for payload in payloads:
            writer.write(payload)
        return writer.num_records
