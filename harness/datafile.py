"""The data-only file format of what the harness reads back from a store: checkpoints and policies.

Reading such a file builds JSON values, NumPy arrays and torch tensors, never objects of classes
named by the file (unlike pickle, ``torch.load(weights_only=False)`` or stable-baselines3's
``.zip``): a file written by someone else who can write to a shared store can be refused, but it
cannot run code. Each file carries a SHA-256 of its content, so a file cut short by a crash (or
changed since it was written) is detected.

Layout, in bytes::

    b"HARNESS-DATA\\n"                  magic
    b"<64 hex digits>\\n"               SHA-256 of everything below this line
    8 bytes, little-endian unsigned    length H of the header
    H bytes                            the header, UTF-8 JSON:
                                       {"format": 1, "kind": "checkpoint" | "policy" | ...,
                                        "meta": {...}, "tree": <tree>,
                                        "arrays": [{"dtype": "<f8", "shape": [2, 3], "offset": 0}, ...]}
    the arrays' bytes                  C order, little-endian, at ``offset`` from the end of the header

The *tree* is JSON, with tagged objects for what JSON lacks: ``{"$tuple": [...]}``,
``{"$dict": [[key, value], ...]}`` (a dict with a key that is not a string or starts with
``$``), ``{"$float": "nan" | "inf" | "-inf"}``, ``{"$array": i}`` (a NumPy array: entry ``i`` of
``arrays``), ``{"$scalar": i}`` (a NumPy scalar), ``{"$tensor": i}`` (a torch tensor). Plain data
therefore round-trips exactly: values bit for bit, dtypes, shapes, tuples as tuples; a mapping comes
back as a ``dict`` and a tensor as a plain tensor that needs no gradient.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import struct
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import CheckpointError

FORMAT = 1
MAGIC = b"HARNESS-DATA\n"
#: the command that converts a run's files in an older, pickled format (see :mod:`harness.migration`)
MIGRATE_COMMAND = "harness store migrate RUN_ID"
#: file suffixes of the formats the harness wrote before this one (pickles, SB3's .zip)
LEGACY_SUFFIXES = (".pkl", ".zip")
#: what a checkpoint and a policy are called in a run (``<prefix>NNN<suffix>``, NNN the trial)
CHECKPOINT_SUFFIX = ".ckpt"
POLICY_SUFFIX = ".policy"

_DTYPES = frozenset(np.dtype(t).newbyteorder("<").str for t in (
    np.bool_, np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32, np.uint64,
    np.float16, np.float32, np.float64, np.complex64, np.complex128))
_HEADER_KEYS = {"format", "kind", "meta", "tree", "arrays"}
_TAGS = {"$tuple", "$dict", "$float", "$array", "$scalar", "$tensor"}
_OLD_CHECKPOINT_MAGIC = b"HARNESS-CKPT\n"
_PICKLE_START = b"\x80"  # PROTO opcode: every pickle of protocol 2 or later
_ZIP_START = b"PK\x03\x04"


class DataFileError(CheckpointError):
    """A file that is not a valid harness data file of the expected kind (cut, changed, foreign)."""


class LegacyFormatError(DataFileError):
    """A file in a format the harness wrote before, whose reading can run code (pickles)."""


class NotPlainDataError(TypeError):
    """An object that a data file cannot hold (it is not plain data); the message names where it is."""


# ------------------------------------------------------------------------------------------------
# encoding
# ------------------------------------------------------------------------------------------------


def _little_endian(array: np.ndarray) -> np.ndarray:
    dtype = array.dtype.newbyteorder("<") if array.dtype.byteorder == ">" else array.dtype
    return np.asarray(array, dtype=dtype, order="C")  # not ascontiguousarray: it makes 0-d arrays 1-d


class _Encoder:
    def __init__(self) -> None:
        self.arrays: list[dict[str, Any]] = []
        self.chunks: list[bytes] = []
        self.offset = 0

    def add(self, array: np.ndarray, where: str) -> int:
        array = _little_endian(array)
        if array.dtype.str not in _DTYPES:
            raise NotPlainDataError(f"{where}: arrays of dtype {array.dtype} cannot be stored (numbers and bools only)")
        data = array.tobytes()
        self.arrays.append({"dtype": array.dtype.str, "shape": list(array.shape), "offset": self.offset})
        self.chunks.append(data)
        self.offset += len(data)
        return len(self.arrays) - 1

    def encode(self, value: Any, where: str) -> Any:
        if value is None or isinstance(value, (bool, str)):
            return value
        if isinstance(value, np.generic):  # before int/float: np.float64 is a float
            return {"$scalar": self.add(np.asarray(value), where)}
        if isinstance(value, int):
            return int(value)
        if isinstance(value, float):
            return float(value) if math.isfinite(value) else {"$float": repr(float(value))}
        if isinstance(value, np.ndarray):
            return {"$array": self.add(value, where)}
        if _is_tensor(value):
            return {"$tensor": self.add(_tensor_to_numpy(value, where), where)}
        if isinstance(value, tuple):
            return {"$tuple": [self.encode(v, f"{where}[{i}]") for i, v in enumerate(value)]}
        if isinstance(value, list):
            return [self.encode(v, f"{where}[{i}]") for i, v in enumerate(value)]
        if isinstance(value, Mapping):
            if all(isinstance(k, str) and not k.startswith("$") for k in value):
                return {k: self.encode(v, f"{where}.{k}") for k, v in value.items()}
            return {"$dict": [[self.encode(k, f"{where} key {k!r}"), self.encode(v, f"{where}[{k!r}]")] for k, v in value.items()]}
        raise NotPlainDataError(
            f"{where} is a {type(value).__module__}.{type(value).__qualname__}: checkpoints and policies hold plain data only "
            "(dict, list, tuple, str, int, float, bool, None, NumPy arrays and scalars, torch tensors)"
        )


def _is_tensor(value: Any) -> bool:
    torch = _torch_if_loaded()
    return torch is not None and isinstance(value, torch.Tensor)


def _torch_if_loaded():
    import sys

    return sys.modules.get("torch")


def _tensor_to_numpy(tensor: Any, where: str) -> np.ndarray:
    import torch

    if tensor.layout != torch.strided or tensor.is_quantized:
        raise NotPlainDataError(f"{where}: only dense tensors can be stored, not {tensor.layout} ones")
    if tensor.dtype == torch.bfloat16:
        raise NotPlainDataError(f"{where}: bfloat16 tensors cannot be stored (convert to float32)")
    return tensor.detach().cpu().contiguous().numpy()


def dumps(kind: str, tree: Any, meta: Mapping[str, Any] | None = None) -> bytes:
    """The bytes of a data file of ``kind`` holding ``tree`` (raises :class:`NotPlainDataError`)."""
    encoder = _Encoder()
    encoded = encoder.encode(tree, kind)
    header = {"format": FORMAT, "kind": kind, "meta": encoder.encode(dict(meta or {}), f"{kind} meta"), "tree": encoded,
              "arrays": encoder.arrays}
    head = json.dumps(header, allow_nan=False, separators=(",", ":")).encode()
    body = struct.pack("<Q", len(head)) + head + b"".join(encoder.chunks)
    return MAGIC + hashlib.sha256(body).hexdigest().encode() + b"\n" + body


def write(path: Path, kind: str, tree: Any, meta: Mapping[str, Any] | None = None) -> Path:
    """Write ``tree`` to ``path`` atomically (temporary file, fsync, rename); returns ``path``."""
    path = Path(path)
    blob = dumps(kind, tree, meta)
    fd, tmp = tempfile.mkstemp(prefix=".data-", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


# ------------------------------------------------------------------------------------------------
# decoding
# ------------------------------------------------------------------------------------------------


class _Invalid(Exception):
    """Something in the header that a valid file cannot hold (the message says what)."""


class _Decoder:
    def __init__(self, specs: Any, data: memoryview) -> None:
        if not isinstance(specs, list):
            raise _Invalid("'arrays' is not a list")
        self.specs, self.data = specs, data

    def array(self, index: Any) -> np.ndarray:
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(self.specs):
            raise _Invalid(f"array reference {index!r} out of range")
        spec = self.specs[index]
        if not isinstance(spec, dict) or set(spec) != {"dtype", "shape", "offset"}:
            raise _Invalid(f"array {index} has keys {sorted(spec) if isinstance(spec, dict) else spec!r}")
        dtype, shape, offset = spec["dtype"], spec["shape"], spec["offset"]
        if dtype not in _DTYPES:
            raise _Invalid(f"array {index} has dtype {dtype!r}")
        if not isinstance(shape, list) or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape):
            raise _Invalid(f"array {index} has shape {shape!r}")
        dt = np.dtype(dtype)
        nbytes = dt.itemsize * math.prod(shape)
        if not isinstance(offset, int) or isinstance(offset, bool) or offset < 0 or offset + nbytes > len(self.data):
            raise _Invalid(f"array {index} lies outside the file")
        return np.frombuffer(self.data[offset:offset + nbytes], dtype=dt).reshape(shape).astype(dt.newbyteorder("="), copy=True)

    def decode(self, node: Any) -> Any:
        if node is None or isinstance(node, (bool, int, float, str)):
            return node
        if isinstance(node, list):
            return [self.decode(v) for v in node]
        if not isinstance(node, dict):
            raise _Invalid(f"unexpected JSON value {node!r}")
        tags = _TAGS.intersection(node)
        if not tags:
            if any(k.startswith("$") for k in node):
                raise _Invalid(f"unknown tag in {sorted(node)}")
            return {k: self.decode(v) for k, v in node.items()}
        if len(node) != 1:
            raise _Invalid(f"unexpected keys {sorted(node)}")
        (tag, value), = node.items()
        if tag == "$tuple":
            if not isinstance(value, list):
                raise _Invalid("$tuple without a list")
            return tuple(self.decode(v) for v in value)
        if tag == "$dict":
            if not isinstance(value, list) or not all(isinstance(p, list) and len(p) == 2 for p in value):
                raise _Invalid("$dict without [key, value] pairs")
            try:
                return {self.decode(k): self.decode(v) for k, v in value}
            except TypeError as exc:  # an unhashable key
                raise _Invalid(f"$dict key: {exc}") from None
        if tag == "$float":
            if value not in ("nan", "inf", "-inf"):
                raise _Invalid(f"$float {value!r}")
            return float(value)
        if tag == "$array":
            return self.array(value)
        if tag == "$scalar":
            array = self.array(value)
            if array.shape != ():
                raise _Invalid("$scalar of an array with a shape")
            return array[()]
        import torch  # a tensor: only files that hold one need torch

        return torch.from_numpy(self.array(value))


def loads(blob: bytes, kind: str, name: str) -> tuple[dict[str, Any], Any]:
    """``(meta, tree)`` of the data file ``blob`` (called ``name`` in messages), which must be of ``kind``.

    Raises:
        LegacyFormatError: a file in an older, pickled format (see :data:`MIGRATE_COMMAND`).
        DataFileError: anything else that is not an intact harness data file of ``kind``.
    """
    if not blob.startswith(MAGIC):
        raise _foreign(blob, kind, name)
    line_end = blob.find(b"\n", len(MAGIC))
    digest, body = blob[len(MAGIC):line_end], blob[line_end + 1:]
    if line_end < 0 or len(body) < 8 or hashlib.sha256(body).hexdigest().encode() != digest:
        raise DataFileError(f"{kind} {name} is corrupt (checksum mismatch: written partially, or changed since it was written)")
    (size,) = struct.unpack("<Q", body[:8])
    try:
        header = json.loads(body[8:8 + size].decode())
        if not isinstance(header, dict) or set(header) != _HEADER_KEYS:
            raise _Invalid(f"header keys {sorted(header) if isinstance(header, dict) else header!r}")
        if header["format"] != FORMAT:
            raise DataFileError(f"{name} has data format {header['format']!r}; this harness reads format {FORMAT}: "
                                "update the harness to read it")
        if header["kind"] != kind:
            raise DataFileError(f"{name} is a harness {header['kind']!r} file, not a {kind}: refused")
        decoder = _Decoder(header["arrays"], memoryview(body)[8 + size:])
        meta, tree = decoder.decode(header["meta"]), decoder.decode(header["tree"])
        if not isinstance(meta, dict):
            raise _Invalid("meta is not a mapping")
    except (_Invalid, ValueError, UnicodeDecodeError) as exc:
        raise DataFileError(f"{kind} {name} is not a valid harness data file ({exc}); it was not written by the harness "
                            "as it is: refused") from None
    return meta, tree


def read(path: Path, kind: str) -> tuple[dict[str, Any], Any]:
    """:func:`loads` of the file at ``path`` (:class:`DataFileError` if it cannot be read)."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise DataFileError(f"cannot read {kind} {path}: {exc.strerror}") from exc
    return loads(blob, kind, path.name)


def _foreign(blob: bytes, kind: str, name: str) -> DataFileError:
    if blob.startswith((_OLD_CHECKPOINT_MAGIC, _PICKLE_START)) or (blob.startswith(_ZIP_START) and name.endswith(".zip")):
        return LegacyFormatError(legacy_message(name, kind))
    return DataFileError(f"{name} is not a harness {kind} file (no harness data header): refused")


def legacy_message(name: str, kind: str, run_id: str | None = None) -> str:
    """The refusal of a file in an older, pickled format, with the command that converts it (for ``run_id``)."""
    command = MIGRATE_COMMAND.replace("RUN_ID", run_id or "RUN_ID")
    return (f"{kind} {name} is in the harness's old pickled format, which can run code when read: not loaded; "
            f"if you trust the store it came from, convert the run's files once with `{command}`")


def is_legacy(name: str) -> bool:
    """Whether an artifact name has the suffix of an older, pickled format."""
    return name.endswith(LEGACY_SUFFIXES)


# ------------------------------------------------------------------------------------------------
# per-trial files of a run
# ------------------------------------------------------------------------------------------------


def trial_files(names: Iterable[str], prefix: str) -> dict[int, str]:
    """``{trial: name}`` of a run's per-trial files ``<prefix>NNN.<suffix>``, ascending by trial; where a
    trial has a file in this format and one in an older format (a migrated run), this format's."""
    pattern = re.compile(rf"(?:^|/){re.escape(prefix)}(\d+)(\.[A-Za-z]+)$")
    found: dict[int, str] = {}
    for name in names:
        match = pattern.search(name)
        if match is None:
            continue
        trial = int(match.group(1))
        if trial not in found or is_legacy(found[trial]) and not is_legacy(name):
            found[trial] = name
    return dict(sorted(found.items()))
