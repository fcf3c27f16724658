"""OpenIGTLink v2 messages: the stream split and checked, images decoded,
results encoded.

The framing is this module's own rather than pyigtl's: a reader that
checks every header, body size and CRC and finds the next header after
garbage bytes (pyigtl checks no CRC, and loses step after garbage), an
IMAGE decoder that says why an image cannot be a frame, a compiled CRC
(:mod:`spheroseg.apps.live.crc`, compiled with the package: every
frame is checked as it is read, every labelmap sent) and a POLYDATA body as
the specification lays it out (pyigtl 0.3 reads no POLYDATA, carries no
attributes and writes vertices in the machine's byte order).  pyigtl is
the tests' reference: what it reads of these messages, they check.

The POLYDATA body (OpenIGTLink ``igtl_polydata.h``), every number big-endian:

- header: 10 ``uint32``: ``NPOINTS``, ``NVERTICES``, ``SIZE_VERTICES``,
  ``NLINES``, ``SIZE_LINES``, ``NPOLYGONS``, ``SIZE_POLYGONS``,
  ``NTRIANGLE_STRIPS``, ``SIZE_TRIANGLE_STRIPS``, ``NATTRIBUTES`` (sizes in
  bytes);
- points: ``NPOINTS x 3`` ``float32`` (x, y, z);
- vertices, lines, polygons, triangle strips: ``uint32`` cells
  ``(N, i1, ..., iN)``;
- per attribute a header of ``uint8`` type (``0x00`` point scalars,
  ``0x10`` cell scalars), ``uint8`` components and ``uint32`` count; then
  the names, each NUL-terminated, padded to an even length; then each
  attribute's ``count x components`` ``float32``.

World coordinates: an IMAGE says whether its matrix is RAS or LPS; a
POLYDATA or a TRANSFORM does not, and 3D Slicer reads them as RAS.
spheroseg works in LPS (ITK); :func:`decode_image` converts what it reads,
the encoders write in the ``coordinates`` asked for.
"""

from __future__ import annotations

import re
import struct
import time
from dataclasses import dataclass

import numpy as np

__all__ = ["HEADER_SIZE", "MAX_BODY_BYTES", "WireError", "Message", "MessageReader", "SectorCache", "pack",
           "check_device", "check_image", "decode_image",
           "encode_image", "encode_polydata", "decode_polydata", "encode_transform", "encode_string",
           "decode_string", "decode_transform", "image_body_size", "set_timestamp", "lps_to"]

HEADER = struct.Struct(">H12s20sIIQQ")
HEADER_SIZE = HEADER.size  # 58
#: the largest body read (bytes); a bigger header is taken for garbage
MAX_BODY_BYTES = 1 << 30
#: the IMAGE body's own header: version, components, scalar type, endianness, coordinates, size (3),
#: matrix (12 float32), subvolume offset (3) and size (3)
IMAGE_HEADER = struct.Struct(">HBBBBHHH12fHHHHHH")
#: OpenIGTLink scalar types as numpy's
SCALAR_TYPES = {2: np.int8, 3: np.uint8, 4: np.int16, 5: np.uint16, 6: np.int32, 7: np.uint32, 10: np.float32,
                11: np.float64}
#: a header's first bytes: version 1 or 2, then a type name (capitals, digits, underscores, NUL-padded)
_HEADER_START = re.compile(rb"\x00[\x01\x02][A-Z][A-Z0-9_]{0,11}\x00*")
#: RAS <-> LPS (its own inverse)
_FLIP = np.diag([-1.0, -1.0, 1.0])


class WireError(ValueError):
    """A message that cannot be used, with ``reason`` (a short key, logged
    once per kind) and the message in words."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass
class Message:
    """One message off the wire, its CRC checked.

    ``received`` is :func:`time.perf_counter` when its last byte was read.
    """

    header_version: int
    type: str
    device: str
    timestamp: float
    body: bytes
    received: float

    @property
    def header_fields(self) -> dict:
        """As ``pyigtl.MessageBase.parse_header`` gives them."""
        return {"header_version": self.header_version, "message_type": self.type, "device_name": self.device,
                "timestamp": self.timestamp, "body_size": len(self.body)}


def _crc64():
    from .crc import crc64

    return crc64


def check_device(device: str) -> str:
    """A device name a header holds: printable ASCII, 20 characters at most."""
    if not (isinstance(device, str) and len(device) <= 20 and all(32 <= ord(c) <= 126 for c in device)):
        raise ValueError(f"a device name is printable ASCII of 20 characters at most, got {device!r}")
    return device


def pack(kind: str, device: str, timestamp: float, content: bytes) -> bytes:
    """A whole message (header version 1): header, then ``content``."""
    check_device(device)
    seconds = int(timestamp)
    fraction = min(int((timestamp - seconds) * 2.0 ** 32), 2 ** 32 - 1)
    return HEADER.pack(1, kind.encode("ascii"), device.encode("ascii"), seconds, fraction, len(content),
                       _crc64()(content)) + content


def _text(field: bytes) -> str | None:
    """A NUL-padded ASCII field; None if something follows the first NUL or
    a byte is not printable."""
    head, _, tail = field.partition(b"\0")
    if tail.strip(b"\0") or any(c < 32 or c > 126 for c in head):
        return None
    return head.decode("ascii")


class MessageReader:
    """Splits a byte stream into checked OpenIGTLink messages.

    :meth:`feed` takes the bytes as they arrive and returns the messages
    completed and the :class:`WireError` of each one skipped: a header that
    is not one (garbage: the stream is searched for the next header), a body
    larger than ``max_body_bytes``, a CRC that does not match (the message is
    skipped, the stream stays in step: its size was read).
    """

    def __init__(self, *, max_body_bytes: int = MAX_BODY_BYTES):
        self.max_body_bytes = int(max_body_bytes)
        self._buffer = bytearray()
        self._header = None  # the current message's header fields, once read
        self.garbage_bytes = 0

    def _parse_header(self, raw: bytes):
        version, kind, device, seconds, fraction, size, crc = HEADER.unpack(raw)
        kind, device = _text(kind), _text(device)
        if version not in (1, 2) or not kind or device is None or not re.fullmatch(r"[A-Z][A-Z0-9_]*", kind):
            return None
        return version, kind, device, seconds + fraction / 2.0 ** 32, size, crc

    def _resync(self, errors: list) -> bool:
        """Drop bytes up to the next plausible header; False if more bytes
        are needed to find one."""
        found = None
        match = _HEADER_START.search(self._buffer, 1)
        while match is not None:  # (not finditer: a failed candidate may overlap the next header)
            start = match.start()
            if len(self._buffer) - start < HEADER_SIZE:
                found = start  # maybe a header: wait for the rest of it
                break
            header = self._parse_header(bytes(self._buffer[start:start + HEADER_SIZE]))
            if header is not None and header[4] <= self.max_body_bytes:
                found = start
                break
            match = _HEADER_START.search(self._buffer, start + 1)
        skipped = len(self._buffer) if found is None else found
        if found is None:
            keep = min(len(self._buffer), HEADER_SIZE - 1)  # a header may start in the last bytes
            skipped -= keep
        del self._buffer[:skipped]
        self.garbage_bytes += skipped
        if skipped:
            errors.append(WireError("garbage", f"{skipped} bytes that are not an OpenIGTLink message skipped"))
        return found is not None and len(self._buffer) >= HEADER_SIZE

    def feed(self, data: bytes) -> list:
        """Messages and :class:`WireError` s, in stream order."""
        self._buffer += data
        out = []
        while True:
            if self._header is None:
                if len(self._buffer) < HEADER_SIZE:
                    return out
                header = self._parse_header(bytes(self._buffer[:HEADER_SIZE]))
                if header is None:
                    if not self._resync(out):
                        return out
                    continue
                if header[4] > self.max_body_bytes:
                    out.append(WireError("body size", f"a message of type {header[1]} and {header[4]} bytes, "
                                                      f"beyond the {self.max_body_bytes} read: skipped as garbage"))
                    del self._buffer[:2]  # not a header to trust: search past it
                    self._resync(out)
                    continue
                del self._buffer[:HEADER_SIZE]
                self._header = header
            version, kind, device, timestamp, size, crc = self._header
            if len(self._buffer) < size:
                return out
            with memoryview(self._buffer) as view:
                body = view[:size].tobytes()  # (one copy; a slice of the bytearray and bytes of it made two)
            del self._buffer[:size]
            self._header = None
            if _crc64()(body) != crc:
                out.append(WireError("crc", f"a message of type {kind} from {device!r} whose CRC does not match "
                                            "its body: skipped"))
                continue
            out.append(Message(version, kind, device, timestamp, body, time.perf_counter()))


def _content(message: Message) -> bytes:
    """The body without a version-2 header's extended header and metadata."""
    body = message.body
    if message.header_version < 2:
        return body
    if len(body) < 12:
        raise WireError("body size", f"a {message.type} message too short for its extended header")
    extended, meta_header, meta_body, _ = struct.unpack(">HHII", body[:12])
    end = len(body) - meta_header - meta_body
    if extended < 12 or end < extended:
        raise WireError("body size", f"a {message.type} message whose extended header does not fit its body")
    return body[extended:end]


def image_body_size(shape, dtype) -> int:
    """Bytes of an IMAGE body (version 1 header) of ``shape`` ``[k, j, i]``."""
    return IMAGE_HEADER.size + int(np.prod(shape)) * np.dtype(dtype).itemsize


def check_image(message: Message) -> dict:
    """An IMAGE message's header, checked, without its voxels read.

    Raises :class:`WireError` (with the reason) for an image that cannot be
    a frame: not a scalar 3D image, a zero or one-voxel dimension, a
    subvolume, an unknown scalar type, voxel data that do not fill the
    declared size, a singular or non-finite matrix.

    Returns
    -------
    dict
        ``content`` (the body), ``dtype``, ``size`` (i, j, k), ``spacing``,
        ``direction``, ``origin`` (world LPS mm) and ``coordinates``
        (``"ras"`` or ``"lps"``, as the message gave its matrix).
    """
    content = _content(message)
    if len(content) < IMAGE_HEADER.size:
        raise WireError("body size", f"an IMAGE of {len(content)} bytes, shorter than its {IMAGE_HEADER.size}-byte "
                                     "header")
    fields = IMAGE_HEADER.unpack_from(content)
    _, components, scalar, endian, system = fields[:5]
    size = np.array(fields[5:8])  # i, j, k
    matrix = np.array(fields[8:20], dtype=float).reshape(4, 3).T  # columns t, s, n, centre
    offset, sub = fields[20:23], np.array(fields[23:26])
    name = f"image {message.device!r}"
    if components != 1:
        raise WireError("components", f"{name} has {components} components per voxel, not one")
    if scalar not in SCALAR_TYPES:
        raise WireError("scalar type", f"{name} has an unknown scalar type {scalar}")
    if np.any(size == 0):
        raise WireError("zero size", f"{name} has a zero dimension ({size[0]} x {size[1]} x {size[2]})")
    if np.any(size < 2):
        raise WireError("2D image", f"{name} is {size[0]} x {size[1]} x {size[2]}: not a 3D image")
    if any(offset) or np.any(sub != size):
        raise WireError("subvolume", f"{name} is a subvolume, which is not read")
    dtype = np.dtype(SCALAR_TYPES[scalar]).newbyteorder("<" if endian == 2 else ">")
    expected = int(np.prod(size)) * dtype.itemsize
    if len(content) - IMAGE_HEADER.size != expected:
        raise WireError("body size", f"{name} declares {size[0]} x {size[1]} x {size[2]} voxels ({expected} bytes) "
                                     f"but carries {len(content) - IMAGE_HEADER.size}")
    axes = matrix[:, :3]
    spacing = np.linalg.norm(axes, axis=0)
    if not np.all(np.isfinite(matrix)) or np.any(spacing <= 0) or abs(np.linalg.det(axes / spacing)) < 1e-6:
        raise WireError("matrix", f"{name} has a singular or non-finite matrix")
    # the message places the image by its centre; the origin is voxel (0, 0, 0)
    origin = matrix[:, 3] - axes @ ((size - 1) / 2.0)
    coordinates = "ras" if system == 1 else "lps"
    if coordinates == "ras":
        axes, origin = _FLIP @ axes, _FLIP @ origin
    return {"content": content, "dtype": dtype, "size": size, "spacing": spacing, "direction": axes / spacing,
            "origin": origin, "coordinates": coordinates, "name": name}


class SectorCache:
    """The sector's padding of the last frame (``no_data_value="auto"``,
    :func:`spheroseg.raster.outside_sector`): a function of the image's
    exact zeros only, found again only when they changed (a scanner's
    sector stays put from frame to frame)."""

    def __init__(self):
        self.zeros = self.padding = None

    def __call__(self, array: np.ndarray):
        from ..._compiled.raster import outside_sector

        zeros = array == 0
        if self.zeros is None or self.zeros.shape != zeros.shape or not np.array_equal(zeros, self.zeros):
            self.zeros, self.padding = zeros, outside_sector(array)
        return self.padding


def decode_image(message: Message, *, no_data_value=None, checked: dict | None = None,
                 sector: SectorCache | None = None):
    """The :class:`spheroseg.Volume` of an IMAGE message (world LPS mm);
    :class:`WireError` as :func:`check_image` (``checked``: what it
    returned, not computed again) or for non-finite voxels.
    ``no_data_value`` as :func:`spheroseg.load`'s; with ``"auto"``,
    ``sector`` keeps the padding from frame to frame.

    Returns
    -------
    volume : Volume
    coordinates : str
        ``"ras"`` or ``"lps"``, as the message gave its matrix.
    """
    from ...io.images import volume_with_no_data
    from ...volumes.volume import Volume

    image = check_image(message) if checked is None else checked
    size = image["size"]
    voxels = np.frombuffer(image["content"], dtype=image["dtype"], offset=IMAGE_HEADER.size)
    voxels = voxels.reshape(size[2], size[1], size[0]).astype(np.float32)
    geometry = dict(spacing=image["spacing"], origin=image["origin"], direction=image["direction"])
    try:
        if sector is not None and isinstance(no_data_value, str) and no_data_value == "auto":
            volume = Volume(voxels, **geometry, no_data_mask=sector(voxels))  # as volume_with_no_data's "auto"
        else:
            volume = volume_with_no_data(voxels, no_data_value, **geometry)
    except ValueError as exc:  # NaN voxels, and such
        raise WireError("voxels", f"{image['name']}: {exc}") from None
    return volume, image["coordinates"]


def lps_to(coordinates: str) -> np.ndarray:
    """The 3x3 map from LPS to ``coordinates`` (``"lps"`` or ``"ras"``)."""
    if coordinates not in ("lps", "ras"):
        raise ValueError(f"coordinates must be 'lps' or 'ras', got {coordinates!r}")
    return _FLIP if coordinates == "ras" else np.eye(3)


#: numpy's types as OpenIGTLink's
_IGTL_TYPES = {np.dtype(t).newbyteorder("<"): code for code, t in SCALAR_TYPES.items()}


def encode_image(array, grid, *, device: str, timestamp: float, coordinates: str = "ras") -> bytes:
    """An IMAGE message of ``array`` ``[z, y, x]`` on ``grid`` (an
    :class:`spheroseg.ImageGrid`, LPS), its matrix in ``coordinates``; the
    voxels little-endian, the matrix placing the image by its centre."""
    flip = lps_to(coordinates)
    array = np.asarray(array)
    if array.dtype == np.bool_:
        array = array.astype(np.uint8)
    array = np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("<"))
    if array.ndim != 3 or array.dtype not in _IGTL_TYPES:
        raise ValueError(f"expected a 3D array of one of {sorted(str(t) for t in _IGTL_TYPES)}, got "
                         f"{array.ndim}D {array.dtype}")
    nz, ny, nx = array.shape
    axes = flip @ (grid.direction * grid.spacing)
    centre = flip @ grid.origin + axes @ ((np.array([nx, ny, nz]) - 1) / 2.0)
    content = IMAGE_HEADER.pack(1, 1, _IGTL_TYPES[array.dtype], 2, 1 if coordinates == "ras" else 2, nx, ny, nz,
                                *axes.T.ravel(), *centre, 0, 0, 0, nx, ny, nz) + array.tobytes()
    return pack("IMAGE", device, timestamp, content)


def set_timestamp(packed: bytes | bytearray, timestamp: float) -> bytes:
    """``packed`` (a whole message) with its header's timestamp replaced
    (the CRC covers the body only)."""
    out = bytearray(packed)
    seconds = int(timestamp)
    struct.pack_into(">II", out, 34, seconds, min(int((timestamp - seconds) * 2.0 ** 32), 2 ** 32 - 1))
    return bytes(out)


def encode_transform(matrix, *, device: str, timestamp: float) -> bytes:
    """A TRANSFORM message of a 4x4 matrix: its 3x4 upper part, column by
    column, float32."""
    matrix = np.asarray(matrix, dtype=float)
    return pack("TRANSFORM", device, timestamp, struct.pack(">12f", *matrix[:3, :4].T.ravel()))


def encode_string(text: str, *, device: str, timestamp: float) -> bytes:
    """A STRING message: ASCII (IANA 3) where it is, else UTF-8 (106)."""
    try:
        encoded, encoding = text.encode("ascii"), 3
    except UnicodeEncodeError:
        encoded, encoding = text.encode("utf8"), 106
    if len(encoded) > 65535:
        raise ValueError(f"a STRING message holds at most 65535 bytes, got {len(encoded)}")
    return pack("STRING", device, timestamp, struct.pack(">HH", encoding, len(encoded)) + encoded)


def decode_string(message: Message) -> str:
    content = _content(message)
    if len(content) < 4:
        raise WireError("body size", "a STRING message shorter than its header")
    encoding, length = struct.unpack_from(">HH", content)
    if len(content) - 4 < length:
        raise WireError("body size", "a STRING message shorter than its declared length")
    return content[4:4 + length].decode("ascii" if encoding == 3 else "utf8")


def decode_transform(message: Message) -> np.ndarray:
    """The 4x4 matrix of a TRANSFORM message."""
    values = struct.unpack(">12f", _content(message)[:48])
    matrix = np.eye(4)
    matrix[:3, :4] = np.array(values).reshape(4, 3).T
    return matrix


_ATTRIBUTE = struct.Struct(">BBI")


def encode_polydata(points, triangles, *, device: str, timestamp: float, point_scalars: dict | None = None) -> bytes:
    """A POLYDATA message of a triangle mesh.

    Parameters
    ----------
    points : array (n, 3)
        In the coordinates the receiver expects (3D Slicer: RAS).
    triangles : int array (m, 3)
    point_scalars : dict, optional
        ``{name: array (n,)}``: one scalar per point each (type ``0x00``).
    """
    points = np.asarray(points, dtype=float)
    triangles = np.asarray(triangles)
    if points.ndim != 2 or points.shape[1] != 3 or triangles.ndim != 2 or triangles.shape[1] != 3:
        raise ValueError(f"expected points (n, 3) and triangles (m, 3), got {points.shape} and {triangles.shape}")
    if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(points)):
        raise ValueError("triangles refer to points that do not exist")
    cells = np.column_stack([np.full(len(triangles), 3), triangles]).astype(">u4")
    scalars = {name: np.asarray(values, dtype=">f4").reshape(-1) for name, values in (point_scalars or {}).items()}
    for name, values in scalars.items():
        if len(values) != len(points):
            raise ValueError(f"attribute {name!r} has {len(values)} values for {len(points)} points")
    header = struct.pack(">10I", len(points), 0, 0, 0, 0, len(triangles), cells.nbytes, 0, 0, len(scalars))
    attribute_headers = b"".join(_ATTRIBUTE.pack(0x00, 1, len(points)) for _ in scalars)
    names = b"".join(name.encode("ascii") + b"\0" for name in scalars)
    names += b"\0" * (len(names) % 2)
    content = (header + points.astype(">f4").tobytes() + cells.tobytes() + attribute_headers + names
               + b"".join(values.tobytes() for values in scalars.values()))
    return pack("POLYDATA", device, timestamp, content)


def decode_polydata(message: Message) -> tuple[np.ndarray, np.ndarray, dict]:
    """Points ``(n, 3)``, triangles ``(m, 3)`` and point scalars of a
    POLYDATA message (its polygons all triangles)."""
    content = _content(message)
    try:
        counts = struct.unpack_from(">10I", content)
        n_points, _, size_vertices, _, size_lines, n_polygons, size_polygons, _, size_strips, n_attributes = counts
        at = 40
        points = np.frombuffer(content, ">f4", 3 * n_points, at).reshape(n_points, 3).astype(float)
        at += 12 * n_points + size_vertices + size_lines
        cells = np.frombuffer(content, ">u4", size_polygons // 4, at).astype(np.int64)
        at += size_polygons + size_strips
        headers = [_ATTRIBUTE.unpack_from(content, at + 6 * k) for k in range(n_attributes)]
        at += 6 * n_attributes
        names = []
        for _ in range(n_attributes):
            end = content.index(b"\0", at)
            names.append(content[at:end].decode("ascii"))
            at = end + 1
        at += sum(len(name) + 1 for name in names) % 2
        attributes = {}
        for name, (_, components, count) in zip(names, headers):
            attributes[name] = np.frombuffer(content, ">f4", count * components, at).astype(float)
            at += 4 * count * components
    except (struct.error, ValueError) as exc:
        raise WireError("body size", f"a POLYDATA message that does not fit its body ({exc})") from None
    triangles = cells.reshape(-1, 4)
    if len(triangles) != n_polygons or np.any(triangles[:, 0] != 3):
        raise WireError("polygons", "a POLYDATA message whose polygons are not all triangles")
    return points, triangles[:, 1:], attributes
