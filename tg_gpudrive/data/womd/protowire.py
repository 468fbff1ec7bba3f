"""Minimal protocol-buffers wire format, so WOMD protos load without protobuf/TensorFlow.

A message is described declaratively by a `Message` holding `Field`s (number,
name, kind, repeated, submessage); `decode(msg, data) -> dict` and
`encode(msg, dict) -> bytes` walk the wire format with those definitions.

Decoded messages are plain dicts that hold only the fields present on the wire
(proto2 presence): absent optional or repeated fields are absent keys, so read
them with `d.get(name, default)`. Value types:

    kind                                  single        repeated
    double float fixed* sfixed*           float / int   np.ndarray (float64, float32, ...)
    int32 int64 uint* sint* enum          int           np.ndarray (int32, int64, ...)
    bool                                  bool          np.ndarray (bool)
    string / bytes                        str / bytes   list
    message                               dict          list of dicts, or dict of columns (`columnar`)

A repeated message field marked `columnar=True` (its message must hold only
single scalar fields, e.g. WOMD ObjectState or MapPoint) decodes to a dict of
NumPy columns, one entry per element, with zeros where an element lacks the
field. Those are the bulk of a WOMD scenario, so elements that share a byte
layout are decoded in one `np.frombuffer` instead of field by field; encode
writes them the same vectorised way.

Decoding accepts repeated scalars packed or unpacked (as protobuf parsers
must); encoding writes them packed only where the field says `packed=True`
(proto2's default is unpacked). Unknown fields are skipped. Not supported:
groups (wire types 3/4, deprecated), maps, extensions, merging of repeated
occurrences of a single message field (the last occurrence wins, whole).
Errors raise `DecodeError` / `EncodeError` carrying a field path like
`tracks[3].states[17].valid` so callers can name what is broken.
"""

from __future__ import annotations

import struct
from collections import defaultdict
from typing import Any, Iterable

import numpy as np

__all__ = ["Field", "Message", "DecodeError", "EncodeError", "decode", "encode",
           "encode_varint", "decode_varint"]

VARINT, I64, LEN, I32 = 0, 1, 2, 5

# kind: (wire type, little-endian NumPy dtype of the value as stored / decoded)
_FIXED = {
    "double": (I64, "<f8"), "fixed64": (I64, "<u8"), "sfixed64": (I64, "<i8"),
    "float": (I32, "<f4"), "fixed32": (I32, "<u4"), "sfixed32": (I32, "<i4"),
}
_VARINT_KINDS = {
    "int32": np.int32, "int64": np.int64, "uint32": np.uint32, "uint64": np.uint64,
    "sint32": np.int32, "sint64": np.int64, "bool": np.bool_, "enum": np.int32,
}
_LEN_KINDS = {"string", "bytes", "message"}
_STRUCTS = {
    "double": struct.Struct("<d"), "fixed64": struct.Struct("<Q"), "sfixed64": struct.Struct("<q"),
    "float": struct.Struct("<f"), "fixed32": struct.Struct("<I"), "sfixed32": struct.Struct("<i"),
}
_INT_RANGE = {
    "int32": (-(1 << 31), 1 << 31), "int64": (-(1 << 63), 1 << 63), "enum": (-(1 << 31), 1 << 31),
    "uint32": (0, 1 << 32), "uint64": (0, 1 << 64),
    "sint32": (-(1 << 31), 1 << 31), "sint64": (-(1 << 63), 1 << 63),
}


class DecodeError(ValueError):
    """Malformed wire data; `field` is the dotted path where decoding failed."""

    def __init__(self, field: str, problem: str):
        self.field, self.problem = field, problem
        super().__init__(f"field '{field}': {problem}" if field else problem)

    def under(self, prefix: str) -> "DecodeError":
        return DecodeError(f"{prefix}.{self.field}" if self.field else prefix, self.problem)


class EncodeError(DecodeError):
    """A dict does not fit its message definition; `field` names the offending value."""

    def under(self, prefix: str) -> "EncodeError":
        return EncodeError(f"{prefix}.{self.field}" if self.field else prefix, self.problem)


# ----------------------------------------------------------------- definitions
class Field:
    """One field of a message definition; see the module docstring for kinds."""

    __slots__ = ("number", "name", "kind", "repeated", "message", "packed", "columnar",
                 "wire_type", "key", "packed_key", "dtype")

    def __init__(self, number: int, name: str, kind: str, repeated: bool = False,
                 message: "Message | None" = None, *, packed: bool = False, columnar: bool = False):
        if kind not in _FIXED and kind not in _VARINT_KINDS and kind not in _LEN_KINDS:
            raise ValueError(f"field {name}: unknown kind {kind!r}")
        if (kind == "message") != (message is not None):
            raise ValueError(f"field {name}: a submessage is needed exactly for kind 'message'")
        if packed and (not repeated or kind in _LEN_KINDS):
            raise ValueError(f"field {name}: only repeated scalar fields can be packed")
        if columnar and not (repeated and kind == "message" and message.flat):
            raise ValueError(f"field {name}: columnar needs a repeated message of single scalars")
        self.number, self.name, self.kind, self.repeated = number, name, kind, repeated
        self.message, self.packed, self.columnar = message, packed, columnar
        self.wire_type = _FIXED[kind][0] if kind in _FIXED else VARINT if kind in _VARINT_KINDS else LEN
        self.key = encode_varint(number << 3 | self.wire_type)
        self.packed_key = encode_varint(number << 3 | LEN)
        self.dtype = (np.dtype(_FIXED[kind][1]).newbyteorder("=") if kind in _FIXED
                      else np.dtype(_VARINT_KINDS[kind]) if kind in _VARINT_KINDS else None)

    def __repr__(self) -> str:
        rep = "repeated " if self.repeated else ""
        sub = self.message.name if self.message else self.kind
        return f"Field({self.number}, {self.name!r}, {rep}{sub})"


class Message:
    """A message definition: a name and its fields (numbers and names unique).

    `fields` is a list of Field, or a dict {number: (name, kind[, repeated[, message]])}.
    """

    def __init__(self, name: str, fields: Iterable[Field] | dict[int, tuple]):
        if isinstance(fields, dict):
            fields = [f if isinstance(f, Field) else Field(num, *f) for num, f in fields.items()]
        self.name = name
        self.fields = sorted(fields, key=lambda f: f.number)  # protobuf writes in number order
        self.by_number = {f.number: f for f in self.fields}
        self.by_name = {f.name: f for f in self.fields}
        if len(self.by_number) != len(self.fields) or len(self.by_name) != len(self.fields):
            raise ValueError(f"message {name}: duplicate field number or name")
        # flat: every field a single scalar, so elements can be decoded as table rows
        self.flat = all(not f.repeated and f.kind not in _LEN_KINDS for f in self.fields)

    def __repr__(self) -> str:
        return f"Message({self.name!r}, {self.fields})"


# ---------------------------------------------------------------------- varint
def encode_varint(value: int) -> bytes:
    """Base-128 varint of a non-negative int below 2**64 (negatives: pass value & (2**64-1))."""
    if value < 0x80:
        return bytes((value,))
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def decode_varint(buf: bytes, pos: int, end: int | None = None) -> tuple[int, int]:
    """Read a varint at `pos`; return (value, position after it)."""
    end = len(buf) if end is None else end
    result = shift = 0
    while True:
        if pos >= end:
            raise DecodeError("", "truncated varint")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if b < 0x80:
            return result, pos
        shift += 7
        if shift >= 70:
            raise DecodeError("", "varint longer than 10 bytes")


def _signed(kind: str, v: int) -> int | bool:
    if kind in ("int32", "int64", "enum"):
        return v - (1 << 64) if v >= 1 << 63 else v
    if kind in ("sint32", "sint64"):
        return (v >> 1) ^ -(v & 1)
    if kind == "bool":
        return v != 0
    return v


# ---------------------------------------------------------------------- decode
def decode(msg: Message, data: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode one serialized message into a dict (see the module docstring)."""
    buf = data if isinstance(data, bytes) else bytes(data)
    return _decode(msg, buf, 0, len(buf))


def _skip(buf: bytes, pos: int, end: int, wt: int, num: int) -> int:
    if wt == VARINT:
        return decode_varint(buf, pos, end)[1]
    if wt == I64:
        pos += 8
    elif wt == I32:
        pos += 4
    elif wt == LEN:
        ln, pos = decode_varint(buf, pos, end)
        pos += ln
    else:
        raise DecodeError(f"#{num}", f"unsupported wire type {wt}")
    if pos > end:
        raise DecodeError(f"#{num}", "truncated unknown field")
    return pos


def _decode(msg: Message, buf: bytes, pos: int, end: int) -> dict[str, Any]:
    """The fields of one `msg` in buf[pos:end]: length-delimited occurrences (sub-messages, columnar ones
    only located; strings, bytes, packed runs) read here, varint and fixed-width ones by `_decode_scalar`;
    repeated fields joined by `_join_repeated`, unknown ones skipped."""
    out: dict[str, Any] = {}
    rep: dict[Field, list] = {}
    by_number = msg.by_number
    while pos < end:
        b = buf[pos]
        if b < 0x80:
            key, pos = b, pos + 1
        else:
            key, pos = decode_varint(buf, pos, end)
        num, wt = key >> 3, key & 7
        f = by_number.get(num)
        if f is None:
            pos = _skip(buf, pos, end, wt, num)
            continue
        kind = f.kind
        if wt == LEN:
            b = buf[pos] if pos < end else 0x80
            if b < 0x80:
                ln, pos = b, pos + 1
            else:
                try:
                    ln, pos = decode_varint(buf, pos, end)
                except DecodeError as e:
                    raise e.under(f.name) from None
            stop = pos + ln
            if stop > end:
                raise DecodeError(f.name, f"length {ln} runs past the end of the enclosing data")
            if kind == "message":
                if f.columnar:
                    rep.setdefault(f, []).append((pos, stop))
                else:
                    parts = rep.setdefault(f, []) if f.repeated else None
                    try:
                        val = _decode(f.message, buf, pos, stop)
                    except DecodeError as e:
                        raise e.under(f"{f.name}[{len(parts)}]" if f.repeated else f.name) from None
                    if f.repeated:
                        parts.append(val)
                    else:
                        out[f.name] = val
            elif kind == "string" or kind == "bytes":
                val = buf[pos:stop]
                if kind == "string":
                    try:
                        val = val.decode("utf-8")
                    except UnicodeDecodeError:
                        raise DecodeError(f.name, "string is not valid UTF-8") from None
                if f.repeated:
                    rep.setdefault(f, []).append(val)
                else:
                    out[f.name] = val
            elif f.repeated:
                rep.setdefault(f, []).append(_unpack(f, buf, pos, stop))
            else:
                raise DecodeError(f.name, f"wire type {wt} does not fit a single {kind}")
            pos = stop
        elif wt == f.wire_type and kind not in _LEN_KINDS:
            pos = _decode_scalar(f, wt, buf, pos, end, out, rep)
        else:
            raise DecodeError(f.name, f"wire type {wt} does not fit kind {kind}")
    _join_repeated(out, rep, buf)
    return out


def _decode_scalar(f: Field, wt: int, buf: bytes, pos: int, end: int, out: dict[str, Any],
                   rep: dict[Field, list]) -> int:
    """One varint or fixed-width occurrence of `f` at `pos` (just past its key); set in `out` or appended
    to `rep`. Returns the position after it."""
    kind = f.kind
    if wt == VARINT:  # a one-byte varint read inline, as in _decode: a helper call per field slows decoding
        b = buf[pos] if pos < end else 0x80
        if b < 0x80:
            v, pos = b, pos + 1
        else:
            try:
                v, pos = decode_varint(buf, pos, end)
            except DecodeError as e:
                raise e.under(f.name) from None
        val = _signed(kind, v)
    else:
        s = _STRUCTS[kind]
        if pos + s.size > end:
            raise DecodeError(f.name, f"truncated {kind}")
        val = s.unpack_from(buf, pos)[0]
        pos += s.size
    if f.repeated:
        rep.setdefault(f, []).append(val)
    else:
        out[f.name] = val
    return pos


def _join_repeated(out: dict[str, Any], rep: dict[Field, list], buf: bytes) -> None:
    """Sets in `out` each repeated field from its collected occurrences: columnar messages as columns,
    messages, strings and bytes as lists, scalars as one array of the field's dtype."""
    for f, parts in rep.items():
        if f.columnar:
            out[f.name] = _columns(f, buf, parts)
        elif f.kind in _LEN_KINDS:
            out[f.name] = parts
        elif all(not isinstance(p, np.ndarray) for p in parts):
            out[f.name] = np.array(parts, dtype=f.dtype)
        else:
            out[f.name] = np.concatenate([np.atleast_1d(np.asarray(p, f.dtype)) for p in parts])


def _unpack(f: Field, buf: bytes, pos: int, stop: int) -> np.ndarray:
    """Decode a packed run of scalars."""
    if f.kind in _FIXED:
        width = f.dtype.itemsize
        if (stop - pos) % width:
            raise DecodeError(f.name, f"packed {f.kind} run of {stop - pos} bytes is not a multiple of {width}")
        return np.frombuffer(buf, _FIXED[f.kind][1], (stop - pos) // width, pos).astype(f.dtype)
    vals = []
    while pos < stop:
        try:
            v, pos = decode_varint(buf, pos, stop)
        except DecodeError as e:
            raise e.under(f.name) from None
        vals.append(_signed(f.kind, v))
    return np.array(vals, dtype=f.dtype)


def _columns(f: Field, buf: bytes, spans: list[tuple[int, int]]) -> dict[str, np.ndarray]:
    """Decode repeated flat messages into columns; equal-layout elements in bulk."""
    msg, n = f.message, len(spans)
    cols = {g.name: np.zeros(n, g.dtype) for g in msg.fields}
    present: set[str] = set()
    groups: dict[int, list[int]] = defaultdict(list)
    for i, (s, e) in enumerate(spans):
        groups[e - s].append(i)
    for length, idx in groups.items():
        if length and _bulk(msg, buf, spans, idx, length, cols, present):
            continue
        for i in idx:  # elements whose layout differs: field by field
            try:
                row = _decode(msg, buf, *spans[i])
            except DecodeError as e:
                raise e.under(f"{f.name}[{i}]") from None
            for name, v in row.items():
                cols[name][i] = v
                present.add(name)
    return {g.name: cols[g.name] for g in msg.fields if g.name in present}


def _layout(msg: Message, buf: bytes, pos: int, end: int):
    """Byte layout of one flat element: (constant byte columns, single-byte varint
    columns, [(field, value offset)]); None when it cannot be decoded as a table
    row (multi-byte varints, length-delimited or repeated fields)."""
    const, varint_cols, values, seen = [], [], [], set()
    start = pos
    while pos < end:
        k0 = pos
        key, pos = decode_varint(buf, pos, end)
        const.extend(range(k0 - start, pos - start))
        num, wt = key >> 3, key & 7
        f = msg.by_number.get(num)
        if num in seen or wt not in (VARINT, I64, I32) or (f is not None and wt != f.wire_type):
            return None
        seen.add(num)
        if wt == VARINT:
            if pos >= end or buf[pos] >= 0x80:
                return None
            varint_cols.append(pos - start)
            width = 1
        else:
            width = 8 if wt == I64 else 4
        if pos + width > end:
            return None
        if f is not None:
            values.append((f, pos - start))
        pos += width
    return const, varint_cols, values


def _bulk(msg, buf, spans, idx, length, cols, present) -> bool:
    s0 = spans[idx[0]][0]
    try:
        layout = _layout(msg, buf, s0, s0 + length)
    except DecodeError:
        return False
    if layout is None:
        return False
    const, varint_cols, values = layout
    raw = b"".join([buf[spans[i][0]:spans[i][1]] for i in idx])
    rows = np.frombuffer(raw, np.uint8).reshape(len(idx), length)
    if len(idx) > 1:
        if const and not (rows[:, const] == rows[0, const]).all():
            return False
        if varint_cols and (rows[:, varint_cols] >= 0x80).any():
            return False
    where = np.asarray(idx)
    for f, off in values:
        if f.kind in _FIXED:
            col = np.ndarray((len(idx),), _FIXED[f.kind][1], raw, off, (length,))
        else:
            col = rows[:, off].astype(np.int64)
            if f.kind in ("sint32", "sint64"):
                col = (col >> 1) ^ -(col & 1)
            elif f.kind == "bool":
                col = col != 0
        cols[f.name][where] = col
        present.add(f.name)
    return True


# ---------------------------------------------------------------------- encode
def encode(msg: Message, value: dict[str, Any]) -> bytes:
    """Serialize a dict shaped like `decode`'s output (None values are skipped)."""
    parts: list[bytes] = []
    _encode(msg, value, parts)
    return b"".join(parts)


def _scalar(f: Field, v: Any) -> bytes:
    kind = f.kind
    if kind in _FIXED:
        try:
            return _STRUCTS[kind].pack(float(v) if kind in ("double", "float") else int(v))
        except (struct.error, TypeError, ValueError) as e:
            raise EncodeError(f.name, f"cannot write {v!r} as {kind}: {e}") from None
    if kind == "bool":
        return b"\x01" if bool(v) else b"\x00"
    try:
        v = int(v)
    except (TypeError, ValueError):
        raise EncodeError(f.name, f"cannot write {v!r} as {kind}") from None
    lo, hi = _INT_RANGE[kind]
    if not lo <= v < hi:
        raise EncodeError(f.name, f"{v} out of range for {kind}")
    if kind in ("sint32", "sint64"):
        v = (v << 1) ^ (v >> 63)
    return encode_varint(v & 0xFFFFFFFFFFFFFFFF)


def _encode(msg: Message, value: dict[str, Any], parts: list[bytes]) -> None:
    if not isinstance(value, dict):
        raise EncodeError("", f"{msg.name} must be a dict, got {type(value).__name__}")
    unknown = set(value) - msg.by_name.keys()
    if unknown:
        raise EncodeError(sorted(unknown)[0], f"not a field of {msg.name}")
    for f in msg.fields:
        v = value.get(f.name)
        if v is None:
            continue
        kind = f.kind
        if not f.repeated:
            if kind == "message":
                sub: list[bytes] = []
                try:
                    _encode(f.message, v, sub)
                except EncodeError as e:
                    raise e.under(f.name) from None
                body = b"".join(sub)
                parts += (f.key, encode_varint(len(body)), body)
            elif kind in ("string", "bytes"):
                body = v.encode("utf-8") if isinstance(v, str) else bytes(v)
                parts += (f.key, encode_varint(len(body)), body)
            else:
                parts += (f.key, _scalar(f, v))
        elif kind == "message":
            if f.columnar and isinstance(v, dict):
                _encode_columns(f, v, parts)
                continue
            for i, item in enumerate(v):
                sub = []
                try:
                    _encode(f.message, item, sub)
                except EncodeError as e:
                    raise e.under(f"{f.name}[{i}]") from None
                body = b"".join(sub)
                parts += (f.key, encode_varint(len(body)), body)
        elif kind in ("string", "bytes"):
            for item in v:
                body = item.encode("utf-8") if isinstance(item, str) else bytes(item)
                parts += (f.key, encode_varint(len(body)), body)
        elif f.packed:
            if len(v):
                body = (np.asarray(v).astype(_FIXED[kind][1]).tobytes() if kind in _FIXED
                        else b"".join(_scalar(f, x) for x in np.asarray(v).tolist()))
                parts += (f.packed_key, encode_varint(len(body)), body)
        else:
            for x in np.asarray(v).tolist():
                parts += (f.key, _scalar(f, x))


def _encode_columns(f: Field, cols: dict[str, Any], parts: list[bytes]) -> None:
    """Write a dict of columns as repeated flat messages, every field in every element."""
    msg = f.message
    unknown = set(cols) - msg.by_name.keys()
    if unknown:
        raise EncodeError(f"{f.name}.{sorted(unknown)[0]}", f"not a field of {msg.name}")
    arrays = [(g, np.asarray(cols[g.name])) for g in msg.fields if cols.get(g.name) is not None]
    sizes = {len(a) for _, a in arrays}
    if len(sizes) > 1:
        raise EncodeError(f.name, f"columns differ in length: {sorted(sizes)}")
    if not arrays or not sizes.pop():
        return
    n = len(arrays[0][1])
    # varint columns go in bulk only while every value fits one byte
    small = []
    for g, a in arrays:
        if g.kind in _FIXED:
            small.append(a)
        elif g.kind == "bool":
            small.append(a.astype(bool).astype(np.uint8))
        else:
            ints = a.astype(np.int64)
            if g.kind in ("sint32", "sint64"):
                ints = (ints << 1) ^ (ints >> 63)
            if ints.min() < 0 or ints.max() >= 0x80:
                rows = [{g.name: a[i] for g, a in arrays} for i in range(n)]
                return _encode_rows(f, rows, parts)
            small.append(ints.astype(np.uint8))
    body_len = sum(len(g.key) + (g.dtype.itemsize if g.kind in _FIXED else 1) for g, _ in arrays)
    prefix = f.key + encode_varint(body_len)
    table = np.empty((n, len(prefix) + body_len), np.uint8)
    table[:, : len(prefix)] = np.frombuffer(prefix, np.uint8)
    off = len(prefix)
    for (g, _), a in zip(arrays, small):
        table[:, off: off + len(g.key)] = np.frombuffer(g.key, np.uint8)
        off += len(g.key)
        if g.kind in _FIXED:
            w = g.dtype.itemsize
            table[:, off: off + w] = np.ascontiguousarray(a, _FIXED[g.kind][1]).view(np.uint8).reshape(n, w)
            off += w
        else:
            table[:, off] = a
            off += 1
    parts.append(table.tobytes())


def _encode_rows(f: Field, rows: list[dict], parts: list[bytes]) -> None:
    for i, row in enumerate(rows):
        sub: list[bytes] = []
        try:
            _encode(f.message, row, sub)
        except EncodeError as e:
            raise e.under(f"{f.name}[{i}]") from None
        body = b"".join(sub)
        parts += (f.key, encode_varint(len(body)), body)
