"""A small CDR (XCDR1, little endian) codec for the ROS 2 message types vmocap uses.

ROS-free: messages are plain dicts keyed by field name (missing fields encode as zero/empty),
numeric arrays decode to numpy arrays, uint8/byte arrays to `bytes`. For encoding, an array of
a struct made of one numeric type (geometry_msgs/Point, std_msgs/ColorRGBA) may be given as a
numpy array (N, fields) instead of a list of dicts. The byte layout is the
one rmw_fastrtps and rosbag2 use (4-byte encapsulation header 00 01 00 00, primitives aligned to
their size relative to the end of the header, strings as uint32 length incl. NUL + bytes + NUL,
sequences as uint32 count + elements), so bags written here play on a real ROS 2 graph and
bytes received raw from rclpy decode here.

`DEFINITIONS` holds the field lists (the ros2msg text without comments or constants) and
`schema_text(type)` the full definition rosbag2 stores in an MCAP schema (the type's own
definition followed by each dependency after a line of 80 '=' and 'MSG: pkg/msg/Type').
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import BagError

DEFINITIONS: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/ColorRGBA": "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n",
    "std_msgs/msg/String": "string data\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose\n",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "sensor_msgs/msg/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
    ),
    "sensor_msgs/msg/Image": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n"
    ),
    "sensor_msgs/msg/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data\n",
    "sensor_msgs/msg/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
        "uint32 binning_y\nRegionOfInterest roi\n"
    ),
    "sensor_msgs/msg/PointField": (
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\n"
        "uint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
        "string name\nuint32 offset\nuint8 datatype\nuint32 count\n"
    ),
    "sensor_msgs/msg/PointCloud2": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\n"
        "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"
    ),
    "sensor_msgs/msg/JointState": (
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
        "float64[] effort\n"
    ),
    "visualization_msgs/msg/UVCoordinate": "float32 u\nfloat32 v\n",
    "visualization_msgs/msg/MeshFile": "string filename\nuint8[] data\n",
    "visualization_msgs/msg/Marker": (
        "int32 ARROW=0\nint32 SPHERE=2\nint32 LINE_LIST=5\nint32 SPHERE_LIST=7\n"
        "int32 ADD=0\nint32 DELETE=2\nint32 DELETEALL=3\n"
        "std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\n"
        "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\n"
        "builtin_interfaces/Duration lifetime\nbool frame_locked\ngeometry_msgs/Point[] points\n"
        "std_msgs/ColorRGBA[] colors\nstring texture_resource\n"
        "sensor_msgs/CompressedImage texture\nUVCoordinate[] uv_coordinates\nstring text\n"
        "string mesh_resource\nMeshFile mesh_file\nbool mesh_use_embedded_materials\n"
    ),
    "visualization_msgs/msg/MarkerArray": "Marker[] markers\n",
    "diagnostic_msgs/msg/KeyValue": "string key\nstring value\n",
    "diagnostic_msgs/msg/DiagnosticStatus": (
        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\n"
        "byte level\nstring name\nstring message\nstring hardware_id\nKeyValue[] values\n"
    ),
    "diagnostic_msgs/msg/DiagnosticArray": "std_msgs/Header header\nDiagnosticStatus[] status\n",
    "rosgraph_msgs/msg/Clock": "builtin_interfaces/Time clock\n",
    "hri_msgs/msg/IdsList": "std_msgs/Header header\nstring[] ids\n",  # ROS4HRI (REP-155), ros/hri_msgs
}

# name -> (struct code, size)
_PRIM: dict[str, tuple[str, int]] = {
    "bool": ("?", 1),
    "byte": ("B", 1),
    "char": ("B", 1),
    "uint8": ("B", 1),
    "int8": ("b", 1),
    "uint16": ("H", 2),
    "int16": ("h", 2),
    "uint32": ("I", 4),
    "int32": ("i", 4),
    "uint64": ("Q", 8),
    "int64": ("q", 8),
    "float32": ("f", 4),
    "float64": ("d", 8),
}
_BYTES = {"uint8", "byte", "char"}
_FIELD_RE = re.compile(r"^([A-Za-z0-9_/]+)(?:<=\d+)?(\[(<=)?(\d*)\])?\s+([a-z][a-z0-9_]*)(\s+.*)?$")
CDR_HEADER = b"\x00\x01\x00\x00"  # CDR little endian, no options


@dataclass(frozen=True)
class _Field:
    name: str
    base: str  # primitive name, "string" or a full type name "pkg/msg/Type"
    array: int | None  # None: scalar, -1: unbounded/bounded sequence, n: fixed array of n
    default: Any = 0  # value of a missing scalar primitive field


def _full_name(base: str, pkg: str) -> str:
    if base in _PRIM or base == "string":
        return base
    if base == "Header":
        return "std_msgs/msg/Header"
    parts = base.split("/")
    if len(parts) == 1:
        return f"{pkg}/msg/{parts[0]}"
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return base


def _parse(type_name: str) -> list[_Field]:
    try:
        text = DEFINITIONS[type_name]
    except KeyError:
        raise BagError(f"message type {type_name!r} is not supported by vmocap's CDR codec") from None
    pkg = type_name.split("/")[0]
    fields = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        head = line.split(None, 1)
        if len(head) == 2 and "=" in head[1]:
            continue  # constant
        m = _FIELD_RE.match(line)
        if m is None:
            raise BagError(f"cannot parse field {line!r} of {type_name}")
        base, arr, _bounded, n, name = m.group(1), m.group(2), m.group(3), m.group(4), m.group(5)
        if arr is None:
            array = None
        elif n and not _bounded:
            array = int(n)
        else:
            array = -1
        default: Any = 0
        if m.group(6) and base in _PRIM and array is None:
            default = float(m.group(6)) if _PRIM[base][0] in "fd" else int(m.group(6))
        fields.append(_Field(name, _full_name(base, pkg), array, default))
    return fields


_FIELDS: dict[str, list[_Field]] = {}


def fields_of(type_name: str) -> list[_Field]:
    if type_name not in _FIELDS:
        _FIELDS[type_name] = _parse(type_name)
    return _FIELDS[type_name]


def dependencies(type_name: str) -> list[str]:
    """Nested types of `type_name` in first-use order (without itself)."""
    out: list[str] = []

    def visit(t: str) -> None:
        for f in fields_of(t):
            if f.base in _PRIM or f.base == "string":
                continue
            if f.base not in out:
                out.append(f.base)
                visit(f.base)

    visit(type_name)
    return out


def schema_text(type_name: str) -> str:
    """Full ros2msg definition of `type_name` as rosbag2 writes it into MCAP schemas."""
    fields_of(type_name)  # BagError for a type the codec does not know
    parts = [DEFINITIONS[type_name].rstrip("\n")]
    for dep in dependencies(type_name):
        parts.append("=" * 80 + f"\nMSG: {dep.replace('/msg/', '/')}\n" + DEFINITIONS[dep].rstrip("\n"))
    return "\n".join(parts) + "\n"


# ----------------------------------------------------------------------------------- encode


class _Out:
    __slots__ = ("parts", "pos")

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.pos = 0

    def align(self, n: int) -> None:
        pad = (-self.pos) % n
        if pad:
            self.parts.append(b"\x00" * pad)
            self.pos += pad

    def put(self, b: bytes) -> None:
        self.parts.append(b)
        self.pos += len(b)


def _enc_prim(out: _Out, base: str, value: Any) -> None:
    code, size = _PRIM[base]
    out.align(size)
    if base == "bool":
        value = bool(value)
    elif code in "fd":
        value = float(value)
    else:
        value = int(value)
    out.put(struct.pack("<" + code, value))


def _enc_string(out: _Out, value: Any) -> None:
    b = (value or "").encode("utf-8") if not isinstance(value, bytes) else value
    out.align(4)
    out.put(struct.pack("<I", len(b) + 1) + b + b"\x00")


def _enc_prim_array(out: _Out, base: str, value: Any, n: int) -> None:
    code, size = _PRIM[base]
    data: bytes | memoryview
    if base in _BYTES:
        # byte views are joined into the output as they are: their payload is copied once, in encode()
        if isinstance(value, np.ndarray):
            data = memoryview(np.ascontiguousarray(value.astype(np.uint8, copy=False))).cast("B")
        elif isinstance(value, memoryview):
            data = value if value.format == "B" and value.ndim == 1 else value.cast("B")
        elif value is None:
            data = b""
        else:
            data = bytes(value)
    else:
        dtype = np.dtype("<" + {"?": "u1"}.get(code, code))
        arr = np.asarray([] if value is None else value).astype(dtype, copy=False).ravel()
        data = arr.tobytes()
    count = len(data) // size
    if n > 0 and count == 0:  # an unset fixed array is zeros
        data, count = b"\x00" * (n * size), n
    _put_block(out, count, n, size, data, "fixed array")


def _put_block(out: _Out, count: int, n: int, size: int, data: Any, what: str) -> None:
    """An array's elements as one block: fixed arrays (n >= 0) must have n elements, sequences
    (n < 0) are prefixed by their uint32 length; the block is aligned to the element size."""
    if n >= 0:
        if count != n:
            raise BagError(f"{what} needs {n} elements, got {count}")
    else:
        out.align(4)
        out.put(struct.pack("<I", count))
    if count:
        out.align(size)
        out.put(data)


def _enc_struct(out: _Out, type_name: str, msg: Any) -> None:
    msg = msg or {}
    for f in fields_of(type_name):
        value = msg.get(f.name) if isinstance(msg, dict) else getattr(msg, f.name, None)
        if f.array is None:
            if f.base == "string":
                _enc_string(out, value)
            elif f.base in _PRIM:
                _enc_prim(out, f.base, f.default if value is None else value)
            else:
                _enc_struct(out, f.base, value)
        elif f.base in _PRIM:
            _enc_prim_array(out, f.base, value, f.array)
        elif isinstance(value, np.ndarray) and _flat_struct(f.base) is not None:
            _enc_flat_struct_array(out, f.base, value, f.array)
        else:
            items = list(value or [])
            if f.array >= 0:
                items += [None] * (f.array - len(items))
            else:
                out.align(4)
                out.put(struct.pack("<I", len(items)))
            if f.base == "string":
                if items:
                    out.align(4)
                    out.put(_string_block(items))
                continue
            for item in items:
                _enc_struct(out, f.base, item)


_STRING_BLOCKS: dict[tuple, bytes] = {}


def _string_block(items: list) -> bytes:
    """CDR of consecutive strings from a 4-aligned position (their layout does not depend on
    where that is), remembered: a JointState's 40 names are the same every frame."""
    key = tuple(items)
    block = _STRING_BLOCKS.get(key)
    if block is None:
        out = _Out()
        for item in key:
            _enc_string(out, item)
        block = b"".join(out.parts)
        if len(_STRING_BLOCKS) < 256:
            _STRING_BLOCKS[key] = block
    return block


_FLAT: dict[str, tuple[str, int] | None] = {}


def _flat_struct(type_name: str) -> tuple[str, int] | None:
    """(primitive, count) of a struct made of one numeric primitive only (Point: float64 x 3,
    ColorRGBA: float32 x 4), whose CDR array is just the numbers back to back; else None."""
    if type_name not in _FLAT:
        fs = fields_of(type_name)
        bases = {f.base for f in fs}
        flat = len(bases) == 1 and all(f.array is None for f in fs) and next(iter(bases)) in _PRIM
        _FLAT[type_name] = (fs[0].base, len(fs)) if flat and fs[0].base not in _BYTES | {"bool"} else None
    return _FLAT[type_name]


def _enc_flat_struct_array(out: _Out, type_name: str, value: np.ndarray, n: int) -> None:
    """An array of flat structs given as a numpy array (N, fields): one block of numbers,
    no per-element Python work."""
    base, k = _flat_struct(type_name)  # type: ignore[misc]
    code, size = _PRIM[base]
    arr = np.ascontiguousarray(value, dtype=np.dtype("<" + code)).reshape(-1, k)
    data = memoryview(arr).cast("B") if len(arr) else b""  # an empty view cannot be cast
    _put_block(out, len(arr), n, size, data, f"fixed array of {type_name}")


# Faster encoders of whole messages, by type: fn(msg) -> the bytes `encode` would give, or None
# when the message does not carry what the fast path needs (see outputs.tf).
FAST_ENCODERS: dict[str, Any] = {}


def encode(type_name: str, msg: Any) -> bytes:
    """CDR bytes (with encapsulation header) of `msg` (a dict) as `type_name`."""
    fast = FAST_ENCODERS.get(type_name)
    if fast is not None:
        data = fast(msg)
        if data is not None:
            return data
    out = _Out()
    _enc_struct(out, type_name, msg)
    return b"".join([CDR_HEADER, *out.parts])  # one copy of the payload (an image's data is MBs)


# ----------------------------------------------------------------------------------- decode


class _In:
    __slots__ = ("buf", "pos", "end", "copy")

    def __init__(self, buf: memoryview, copy: bool = True) -> None:
        self.buf = buf
        self.pos = 0
        self.end = len(buf)
        self.copy = copy

    def align(self, n: int) -> None:
        self.pos += (-self.pos) % n

    def take(self, n: int) -> memoryview:
        if self.pos + n > self.end:
            raise BagError(f"CDR message truncated: need {n} bytes at offset {self.pos} of {self.end}")
        b = self.buf[self.pos : self.pos + n]
        self.pos += n
        return b


def _dec_prim(inp: _In, base: str) -> Any:
    code, size = _PRIM[base]
    inp.align(size)
    return struct.unpack("<" + code, inp.take(size))[0]


def _dec_string(inp: _In) -> str:
    inp.align(4)
    n = struct.unpack("<I", inp.take(4))[0]
    raw = bytes(inp.take(n))
    return raw[:-1].decode("utf-8", errors="replace") if n else ""


def _dec_struct(inp: _In, type_name: str) -> dict:
    msg: dict[str, Any] = {}
    for f in fields_of(type_name):
        if f.array is None:
            if f.base == "string":
                msg[f.name] = _dec_string(inp)
            elif f.base in _PRIM:
                msg[f.name] = _dec_prim(inp, f.base)
            else:
                msg[f.name] = _dec_struct(inp, f.base)
            continue
        if f.array >= 0:
            count = f.array
        else:
            inp.align(4)
            count = struct.unpack("<I", inp.take(4))[0]
        if f.base in _PRIM:
            code, size = _PRIM[f.base]
            if count:
                inp.align(size)
            raw = inp.take(count * size)
            if f.base in _BYTES:
                msg[f.name] = bytes(raw) if inp.copy else raw.toreadonly()
            else:
                dtype = np.dtype("<" + {"?": "u1"}.get(code, code))
                arr = np.frombuffer(raw, dtype=dtype).copy()
                msg[f.name] = arr.astype(bool) if code == "?" else arr
        elif f.base == "string":
            msg[f.name] = [_dec_string(inp) for _ in range(count)]
        else:
            msg[f.name] = [_dec_struct(inp, f.base) for _ in range(count)]
    return msg


def decode(type_name: str, data: bytes | memoryview, copy: bool = True) -> dict:
    """Decode CDR bytes (with encapsulation header) of a `type_name` message into a dict.
    copy=False: byte arrays (uint8[] such as Image.data) are read-only memoryviews into `data`
    instead of copies (an image is not copied once more on its way to numpy)."""
    mv = memoryview(data)
    if len(mv) < 4:
        raise BagError(f"CDR message of {type_name} too short ({len(mv)} bytes)")
    if mv[1] != 1:
        raise BagError(f"{type_name}: only little-endian CDR is supported (header {bytes(mv[:4]).hex()})")
    return _dec_struct(_In(mv[4:], copy), type_name)
