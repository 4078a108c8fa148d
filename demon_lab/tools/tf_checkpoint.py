"""A reader of TensorFlow's checkpoint V2 format, the files ``tf.train.Saver`` writes since
TensorFlow 1.0 (DeMoN's released ``demon_original`` is one), without TensorFlow.

A checkpoint is a prefix and its files:

- ``PREFIX.index``: a sorted string table in LevelDB's format (data blocks of prefix-compressed
  entries, an index block, a 48-byte footer ending in the table magic). The entry with the empty
  key holds a ``BundleHeaderProto`` (number of shards, endianness); every other key is a tensor's
  name and holds a ``BundleEntryProto``: dtype, shape, shard, byte offset, byte size and the
  masked CRC32C of the bytes (TensorFlow's ``tensorflow/core/protobuf/tensor_bundle.proto``).
- ``PREFIX.data-SSSSS-of-NNNNN``: the tensors' raw bytes, shard by shard, in C order.

:class:`CheckpointReader` parses the index (checking every block's checksum) and reads tensors
as numpy arrays, checking each one's size against its shard and its CRC32C. Anything that does
not hold is one :class:`CheckpointFormatError` line. ``tests/test_convert.py`` checks the reader
against TensorFlow's own on checkpoints TensorFlow writes.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path

import google_crc32c
import numpy as np

TABLE_MAGIC = 0xDB4775248B80FB57
FOOTER_SIZE = 48
BLOCK_TRAILER_SIZE = 5  # compression type (1 byte) + masked CRC32C (4 bytes)

# TensorFlow's DataType enum (tensorflow/core/framework/types.proto) -> numpy dtype.
DTYPES = {1: np.float32, 2: np.float64, 3: np.int32, 4: np.uint8, 5: np.int16, 6: np.int8, 9: np.int64,
          10: np.bool_, 17: np.uint16, 19: np.float16, 22: np.uint32, 23: np.uint64}
DTYPE_NAMES = {7: "string", 14: "bfloat16", 8: "complex64", 18: "complex128", 20: "resource", 21: "variant"}


class CheckpointFormatError(ValueError):
    """The files are not a readable checkpoint (one line naming the file and what is wrong)."""


def _unmask(masked: int) -> int:
    """Undo LevelDB's / TensorFlow's CRC masking (``crc32c::Unmask``)."""
    rot = (masked - 0xA282EAD8) & 0xFFFFFFFF
    return ((rot >> 17) | (rot << 15)) & 0xFFFFFFFF


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= len(buf) or shift > 63:
            raise IndexError("varint runs past its buffer")
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, pos
        shift += 7


def _fields(message: bytes) -> dict[int, list]:
    """A protobuf message's fields: number -> values (varints as int, length-delimited as bytes)."""
    fields: dict[int, list] = {}
    pos = 0
    while pos < len(message):
        tag, pos = _varint(message, pos)
        number, wire = tag >> 3, tag & 7
        if wire == 0:
            value, pos = _varint(message, pos)
        elif wire == 1:
            value, pos = struct.unpack_from("<Q", message, pos)[0], pos + 8
        elif wire == 2:
            length, pos = _varint(message, pos)
            value, pos = message[pos:pos + length], pos + length
            if pos > len(message):
                raise IndexError("field runs past its message")
        elif wire == 5:
            value, pos = struct.unpack_from("<I", message, pos)[0], pos + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
        fields.setdefault(number, []).append(value)
    return fields


def _signed(value: int) -> int:
    return value - (1 << 64) if value >= 1 << 63 else value


@dataclass(frozen=True)
class TensorEntry:
    """Where one tensor lives (a ``BundleEntryProto``)."""

    name: str
    dtype: int  # TensorFlow DataType enum
    shape: tuple[int, ...]
    shard: int
    offset: int
    size: int
    crc32c: int | None  # unmasked; None when the entry has none
    sliced: bool  # a partitioned variable (stored as slices)

    @property
    def dtype_name(self) -> str:
        if self.dtype in DTYPES:
            return np.dtype(DTYPES[self.dtype]).name
        return DTYPE_NAMES.get(self.dtype, f"dtype {self.dtype}")


def _entry(name: str, message: bytes) -> TensorEntry:
    f = _fields(message)
    shape: list[int] = []
    for shape_message in f.get(2, []):
        for dim in _fields(shape_message).get(2, []):
            shape.append(_signed(_fields(dim).get(1, [0])[0]))
    crc = f.get(6, [None])[0]
    return TensorEntry(name, f.get(1, [0])[0], tuple(shape), f.get(3, [0])[0], f.get(4, [0])[0], f.get(5, [0])[0],
                       None if crc is None else _unmask(crc), bool(f.get(7)))


class CheckpointReader:
    """The tensors of the checkpoint ``prefix`` (``PREFIX.index`` + ``PREFIX.data-*``).

    ``prefix`` may also be given as the path of its ``.index`` or one of its ``.data-*`` files.
    """

    def __init__(self, prefix: str | Path):
        self.prefix = Path(normalise_prefix(prefix))
        index = Path(f"{self.prefix}.index")
        if not index.is_file():
            raise CheckpointFormatError(f"{index}: no such file (a checkpoint is PREFIX.index + PREFIX.data-*)")
        self._index_path = index
        table = index.read_bytes()
        try:
            entries = dict(self._read_table(table))
            header = entries.pop("", None)
            if header is None:
                raise ValueError("no bundle header")
            h = _fields(header)
            self.num_shards = h.get(1, [1])[0]
            if not isinstance(self.num_shards, int) or not 0 < self.num_shards < 1 << 20:
                raise ValueError(f"a bundle header with {self.num_shards!r} shards")
            big_endian = h.get(2, [0])[0] != 0
            self.entries = {name: _entry(name, value) for name, value in entries.items()}
        except (IndexError, ValueError, TypeError, UnicodeDecodeError, struct.error) as e:
            raise CheckpointFormatError(f"{index}: not a TensorFlow checkpoint index ({e})") from None
        if big_endian:
            raise CheckpointFormatError(f"{index}: a big-endian checkpoint; only little-endian ones are supported")
        self.shards = [Path(f"{self.prefix}.data-{i:05d}-of-{self.num_shards:05d}") for i in range(self.num_shards)]
        for entry in self.entries.values():
            shard = self._shard(entry)
            if entry.offset + entry.size > shard.stat().st_size:
                raise CheckpointFormatError(
                    f"{shard}: truncated: {entry.name} needs bytes {entry.offset}..{entry.offset + entry.size} "
                    f"of a {shard.stat().st_size}-byte file")

    def _shard(self, entry: TensorEntry) -> Path:
        if not 0 <= entry.shard < self.num_shards:
            raise CheckpointFormatError(f"{self._index_path}: {entry.name} is in shard {entry.shard} of "
                                        f"{self.num_shards}")
        shard = self.shards[entry.shard]
        if not shard.is_file():
            raise CheckpointFormatError(f"{shard}: no such file (the data shard of {entry.name})")
        return shard

    @staticmethod
    def _block(table: bytes, handle: bytes) -> bytes:
        offset, pos = _varint(handle, 0)
        size, _ = _varint(handle, pos)
        end = offset + size
        if end + BLOCK_TRAILER_SIZE > len(table):
            raise ValueError(f"truncated: a block ends at byte {end + BLOCK_TRAILER_SIZE} of {len(table)}")
        block, kind = table[offset:end], table[end]
        if kind != 0:
            raise ValueError(f"a compressed block (type {kind}); TensorFlow writes its indexes uncompressed")
        stored = _unmask(struct.unpack_from("<I", table, end + 1)[0])
        if google_crc32c.value(table[offset:end + 1]) != stored:
            raise ValueError(f"checksum mismatch in the block at byte {offset}")
        return block

    @staticmethod
    def _entries(block: bytes):
        if len(block) < 4:
            raise ValueError("a block shorter than its restart count")
        restarts = struct.unpack_from("<I", block, len(block) - 4)[0]
        limit = len(block) - 4 * (restarts + 1)
        if limit < 0:
            raise ValueError("a block shorter than its restart array")
        pos, key = 0, b""
        while pos < limit:
            shared, pos = _varint(block, pos)
            unshared, pos = _varint(block, pos)
            length, pos = _varint(block, pos)
            key = key[:shared] + block[pos:pos + unshared]
            pos += unshared
            yield key, block[pos:pos + length]
            pos += length

    def _read_table(self, table: bytes):
        if len(table) < FOOTER_SIZE:
            raise ValueError(f"truncated: {len(table)} bytes, shorter than the {FOOTER_SIZE}-byte footer")
        footer = table[-FOOTER_SIZE:]
        if struct.unpack_from("<Q", footer, FOOTER_SIZE - 8)[0] != TABLE_MAGIC:
            raise ValueError("no table magic at its end (truncated, or not an index file)")
        _, pos = _varint(footer, 0)
        _, pos = _varint(footer, pos)  # the metaindex handle (TensorFlow leaves it empty)
        index_handle = footer[pos:]
        for _, handle in self._entries(self._block(table, index_handle)):
            for key, value in self._entries(self._block(table, handle)):
                yield key.decode("utf-8"), value

    def read(self, name: str) -> np.ndarray:
        """The tensor ``name`` as a numpy array (its size and CRC32C checked)."""
        entry = self.entries[name]
        shard = self._shard(entry)
        if entry.sliced:
            raise CheckpointFormatError(f"{self._index_path}: {name} is a partitioned variable; only whole "
                                        "variables are supported")
        if entry.dtype not in DTYPES:
            raise CheckpointFormatError(f"{self._index_path}: {name} has dtype {entry.dtype_name}, which this "
                                        "reader does not read")
        dtype = np.dtype(DTYPES[entry.dtype]).newbyteorder("<")
        count = int(np.prod(entry.shape, dtype=np.int64))
        if any(d < 0 for d in entry.shape) or count * dtype.itemsize != entry.size:
            raise CheckpointFormatError(f"{self._index_path}: {name}: {entry.size} bytes for shape "
                                        f"{list(entry.shape)} of {entry.dtype_name}")
        with open(shard, "rb") as f:
            f.seek(entry.offset)
            raw = f.read(entry.size)
        if len(raw) != entry.size:
            raise CheckpointFormatError(f"{shard}: truncated: {name} has {len(raw)} of its {entry.size} bytes")
        if entry.crc32c is not None and google_crc32c.value(raw) != entry.crc32c:
            raise CheckpointFormatError(f"{shard}: checksum mismatch in {name} (a corrupt or changed file)")
        return np.frombuffer(raw, dtype=dtype).reshape(entry.shape).copy()


def normalise_prefix(path: str | Path) -> str:
    """A checkpoint's prefix from the prefix itself or the path of one of its files."""
    text = str(path)
    if text.endswith(".index"):
        return text[: -len(".index")]
    shard = re.search(r"\.data-\d{5}-of-\d{5}$", text)
    return text[: shard.start()] if shard else text
