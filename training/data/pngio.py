"""8-bit PNG read/write with OpenCV's conventions, and a numpy + zlib fallback when OpenCV is missing.

The offline GPU machine has no OpenCV, yet `cmnav dataset` writes PNGs and the TartanAir loader reads
them there.  :func:`read_png` / :func:`write_png` use cv2 when it imports (so behaviour is unchanged
where it does) and :func:`decode_png` / :func:`encode_png` otherwise.  Arrays follow
``cv2.imread(path, cv2.IMREAD_UNCHANGED)``: uint8 (H, W) gray, (H, W, 3) BGR or (H, W, 4) BGRA.

The fallback reads 8-bit gray, gray+alpha (returned as BGRA, as OpenCV does), RGB and RGBA,
non-interlaced, with any of the five row filters; it refuses 16-bit, palette, sub-byte, interlaced
and tRNS-transparency files with a message that names the file.  It writes every row with the Up
filter (vectorised, and smaller than no filter on rendered images).
"""

from __future__ import annotations

import functools
import struct
import zlib
from pathlib import Path
from types import ModuleType

import numpy as np

SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # PNG colour type -> samples per pixel (8-bit only)
_COLOR_TYPE = {1: 0, 3: 2, 4: 6}  # channels of the array to write -> PNG colour type
_INSTALL_HINT = "install opencv-python-headless to read it"


class PngError(ValueError):
    """A file is missing, not a PNG, or a PNG this module cannot read; the message names it."""


@functools.cache
def opencv() -> ModuleType | None:
    """cv2, or None where OpenCV is not installed (the offline GPU machine)."""
    try:
        import cv2
    except ImportError:
        return None
    return cv2


def read_png(path: str | Path) -> np.ndarray:
    """uint8 (H, W) gray, (H, W, 3) BGR or (H, W, 4) BGRA, as cv2.imread(IMREAD_UNCHANGED) gives."""
    cv2 = opencv()
    if cv2 is not None:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise PngError(f"cannot read image {path}: missing or not an image file")
        return image
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise PngError(f"cannot read image {path}: {err}") from err
    return decode_png(data, str(path))


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write uint8 (H, W) gray, (H, W, 3) BGR or (H, W, 4) BGRA as a PNG; OSError if it fails."""
    cv2 = opencv()
    if cv2 is not None:
        if not cv2.imwrite(str(path), image):
            raise OSError(f"could not write {path}: is the directory there and the disk not full?")
        return
    Path(path).write_bytes(encode_png(image))


def encode_png(image: np.ndarray) -> bytes:
    """uint8 (H, W), (H, W, 1), BGR (H, W, 3) or BGRA (H, W, 4) -> PNG file bytes (Up filter)."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    channels = 1 if image.ndim == 2 else image.shape[2] if image.ndim == 3 else 0
    if image.dtype != np.uint8 or channels not in _COLOR_TYPE or min(image.shape[:2], default=0) < 1:
        raise ValueError(f"expected a uint8 image (H, W), (H, W, 3) or (H, W, 4), got {image.dtype} {image.shape}")
    height, width = image.shape[:2]
    if channels >= 3:
        image = image[..., [2, 1, 0, 3][:channels]]  # BGR(A) in memory, RGB(A) in the file
    rows = np.ascontiguousarray(image).reshape(height, width * channels)
    up = np.empty((height, width * channels + 1), np.uint8)
    up[:, 0] = 2  # filter type Up
    up[0, 1:] = rows[0]
    np.subtract(rows[1:], rows[:-1], out=up[1:, 1:])  # uint8 arithmetic wraps modulo 256, as PNG wants
    header = struct.pack(">IIBBBBB", width, height, 8, _COLOR_TYPE[channels], 0, 0, 0)
    return SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(up.tobytes(), 6)) + _chunk(b"IEND", b"")


def decode_png(data: bytes, name: str = "<bytes>") -> np.ndarray:
    """PNG file bytes -> uint8 array in OpenCV's layout (see the module docstring).  ``name`` is
    the file the bytes came from, for error messages."""
    if not data.startswith(SIGNATURE):
        raise PngError(f"{name} is not a PNG file (without OpenCV only PNG is read: {_INSTALL_HINT})")
    header, idat, pos = None, [], len(SIGNATURE)
    while True:
        if pos + 8 > len(data):
            raise PngError(f"{name} is truncated (no IEND chunk): re-write or remove it")
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        crc = data[pos + 8 + length : pos + 12 + length]
        if len(body) != length or len(crc) != 4:
            raise PngError(f"{name} is truncated in its {kind!r} chunk: re-write or remove it")
        if zlib.crc32(kind + body) != struct.unpack(">I", crc)[0]:
            raise PngError(f"{name} is corrupt (CRC mismatch in its {kind!r} chunk): re-write or remove it")
        pos += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"tRNS":
            raise PngError(f"{name} has tRNS transparency, which the numpy PNG reader does not handle: {_INSTALL_HINT}")
        elif kind == b"IEND":
            break
    if header is None:
        raise PngError(f"{name} has no IHDR chunk: re-write or remove it")
    width, height, bit_depth, color_type, _, _, interlace = header
    if bit_depth != 8 or color_type not in _CHANNELS:
        raise PngError(
            f"{name} is a {bit_depth}-bit PNG of colour type {color_type}; the numpy PNG reader reads only 8-bit "
            f"gray, gray+alpha, RGB and RGBA: {_INSTALL_HINT}"
        )
    if interlace != 0:
        raise PngError(f"{name} is an interlaced (Adam7) PNG, which the numpy PNG reader does not handle: {_INSTALL_HINT}")
    channels = _CHANNELS[color_type]
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as err:
        raise PngError(f"{name} has corrupt image data ({err}): re-write or remove it") from err
    stride = 1 + width * channels  # a filter-type byte, then the row's samples
    if len(raw) != height * stride:
        raise PngError(f"{name} holds {len(raw)} bytes of pixels, expected {height * stride}: re-write or remove it")
    pixels = _unfilter(np.frombuffer(raw, np.uint8).reshape(height, stride), channels, name)
    image = pixels.reshape(height, width, channels)
    if channels == 1:
        return image[..., 0]
    if channels == 2:  # gray+alpha: OpenCV gives BGRA
        return np.concatenate([np.repeat(image[..., :1], 3, axis=2), image[..., 1:]], axis=2)
    return np.ascontiguousarray(image[..., [2, 1, 0, 3][:channels]])


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _unfilter(rows: np.ndarray, bpp: int, name: str) -> np.ndarray:
    """Undo the per-row filters (PNG spec 9.2).  None/Sub/Up are vectorised; Average and Paeth
    depend on the reconstructed left neighbour, so they run byte by byte on Python ints."""
    height, stride = rows.shape[0], rows.shape[1] - 1
    out = np.empty((height, stride), np.uint8)
    prior = np.zeros(stride, np.uint8)
    for y in range(height):
        kind, line = int(rows[y, 0]), rows[y, 1:]
        if kind == 0:
            out[y] = line
        elif kind == 1:  # Sub: a running sum of each channel along the row, modulo 256
            out[y] = np.cumsum(line.reshape(-1, bpp), axis=0, dtype=np.uint8).reshape(-1)
        elif kind == 2:
            np.add(line, prior, out=out[y])
        elif kind == 3:
            out[y] = _unfilter_average(line.tolist(), prior.tolist(), bpp)
        elif kind == 4:
            out[y] = _unfilter_paeth(line.tolist(), prior.tolist(), bpp)
        else:
            raise PngError(f"{name} row {y} has filter type {kind} (valid: 0-4): the file is corrupt")
        prior = out[y]
    return out


def _unfilter_average(line: list[int], prior: list[int], bpp: int) -> bytearray:
    cur = bytearray(len(line))
    for i in range(bpp):
        cur[i] = (line[i] + (prior[i] >> 1)) & 0xFF
    for i in range(bpp, len(line)):
        cur[i] = (line[i] + ((cur[i - bpp] + prior[i]) >> 1)) & 0xFF
    return cur


def _unfilter_paeth(line: list[int], prior: list[int], bpp: int) -> bytearray:
    cur = bytearray(len(line))
    for i in range(bpp):  # no left neighbour: a = c = 0, so Paeth picks b
        cur[i] = (line[i] + prior[i]) & 0xFF
    for i in range(bpp, len(line)):
        a, b, c = cur[i - bpp], prior[i], prior[i - bpp]
        pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
        cur[i] = (line[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 0xFF
    return cur
