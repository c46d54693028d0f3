"""An ONNX model with another input height and width, rewritten in memory (no ``onnx`` package needed).

YOLOX-Nano is exported for a 416 x 416 input, and a 640 x 480 frame fills 416 x 312 of it: a quarter of the
network's work is spent on the letterbox's padding. Its graph holds no size of its own (its reshapes are
``[1, 85, -1]``, its upsampling a scale, its slices open-ended), so it runs on 416 x 320 as well; only the
declared input shape, the declared output shape and the intermediate shapes recorded at export
(``value_info``) name the old size, and ONNX Runtime refuses an input that does not match the declaration.
``with_input_size`` sets the input's height and width, leaves the outputs' dimensions unknown and drops the
recorded intermediate shapes (ONNX Runtime infers them again).

The model is a protobuf message; this walks the few fields on the way (ModelProto.graph -> GraphProto.input
/ output / value_info -> ValueInfoProto.type -> TypeProto.tensor_type -> .shape -> .dim -> .dim_value) and
copies every other field's bytes unchanged.
"""
from __future__ import annotations

# Field numbers of onnx.proto3 (ONNX IR >= 3).
_MODEL_GRAPH = 7
_GRAPH_INPUT, _GRAPH_OUTPUT, _GRAPH_VALUE_INFO = 11, 12, 13
_VALUE_INFO_TYPE = 2
_TYPE_TENSOR = 1
_TENSOR_SHAPE = 2
_SHAPE_DIM = 1
_DIM_VALUE = 1

_VARINT, _FIXED64, _BYTES, _FIXED32 = 0, 1, 2, 5

# The detector models whose graphs hold no input size of their own: YOLOX-Nano (above). NanoDet-m's channel
# shuffles reshape to fixed sizes, so it keeps its square input.
SIZE_FREE_MODELS = frozenset({"yolox_nano"})


class OnnxRewriteError(ValueError):
    """The bytes are not the model this expects (not a protobuf of that layout, no 4-D first input)."""


def _read_varint(buf: bytes, pos: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if pos >= len(buf):
            raise OnnxRewriteError("truncated varint")
        byte = buf[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise OnnxRewriteError("varint longer than 64 bits")


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _fields(buf: bytes) -> list[tuple[int, int, bytes]]:
    """(field number, wire type, the field's whole encoding: tag and value) of every field, in order."""
    out, pos = [], 0
    while pos < len(buf):
        start = pos
        tag, pos = _read_varint(buf, pos)
        number, wire = tag >> 3, tag & 7
        if wire == _VARINT:
            _, pos = _read_varint(buf, pos)
        elif wire == _FIXED64:
            pos += 8
        elif wire == _FIXED32:
            pos += 4
        elif wire == _BYTES:
            length, pos = _read_varint(buf, pos)
            pos += length
        else:
            raise OnnxRewriteError(f"unsupported protobuf wire type {wire}")
        if pos > len(buf):
            raise OnnxRewriteError("truncated field")
        out.append((number, wire, buf[start:pos]))
    return out


def _payload(encoded: bytes) -> bytes:
    """The value of a length-delimited field's encoding."""
    _, pos = _read_varint(encoded, 0)
    length, pos = _read_varint(encoded, pos)
    return encoded[pos:pos + length]


def _message_field(number: int, payload: bytes) -> bytes:
    return _varint(number << 3 | _BYTES) + _varint(len(payload)) + payload


def _rewrite(buf: bytes, number: int, change, which: str = "all") -> bytes:
    """``buf`` with each length-delimited field ``number`` (or only the first: ``which='first'``) replaced by
    ``change(payload)``; a None from ``change`` drops the field."""
    parts, done = [], False
    for field, wire, encoded in _fields(buf):
        if field == number and wire == _BYTES and not (done and which == "first"):
            done = True
            new = change(_payload(encoded))
            if new is not None:
                parts.append(_message_field(number, new))
        else:
            parts.append(encoded)
    if not done:
        raise OnnxRewriteError(f"field {number} not found")
    return b"".join(parts)


def _set_dims(shape: bytes, values: dict[int, int]) -> bytes:
    """A TensorShapeProto with dim[i].dim_value = values[i]."""
    parts, index = [], 0
    for field, wire, encoded in _fields(shape):
        if field == _SHAPE_DIM and wire == _BYTES:
            if index in values:
                encoded = _message_field(_SHAPE_DIM, _varint(_DIM_VALUE << 3 | _VARINT) + _varint(values[index]))
            index += 1
        parts.append(encoded)
    if index != 4:
        raise OnnxRewriteError(f"the first input has {index} dimensions, expected 4 (N, C, H, W)")
    return b"".join(parts)


def _in_tensor_type(value_info: bytes, change) -> bytes:
    return _rewrite(value_info, _VALUE_INFO_TYPE, lambda t: _rewrite(t, _TYPE_TENSOR, change))


def _unknown_dims(shape: bytes) -> bytes:
    """A TensorShapeProto of the same rank with every dimension unknown (an empty Dimension)."""
    return b"".join(_message_field(_SHAPE_DIM, b"") if field == _SHAPE_DIM else enc
                    for field, _, enc in _fields(shape))


def with_input_size(model: bytes, height: int, width: int) -> bytes:
    """The serialized model ``model`` with its first input's height and width set to ``height`` x ``width``,
    its outputs' dimensions unknown and its recorded intermediate shapes removed."""
    if height <= 0 or width <= 0:
        raise ValueError(f"input size must be positive, got {height} x {width}")

    def graph(g: bytes) -> bytes:
        g = _rewrite(g, _GRAPH_INPUT, lambda vi: _in_tensor_type(
            vi, lambda tt: _rewrite(tt, _TENSOR_SHAPE, lambda s: _set_dims(s, {2: height, 3: width}))), "first")
        g = _rewrite(g, _GRAPH_OUTPUT, lambda vi: _in_tensor_type(
            vi, lambda tt: _rewrite(tt, _TENSOR_SHAPE, _unknown_dims)))
        return b"".join(enc for field, _, enc in _fields(g) if field != _GRAPH_VALUE_INFO)

    return _rewrite(model, _MODEL_GRAPH, graph, "first")
