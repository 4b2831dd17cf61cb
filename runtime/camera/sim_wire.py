"""Wire format of the SITL camera link (TCP on 127.0.0.1): one message per frame.

Header (little endian, 32 bytes): magic ``b"CMNF"``, version u32, seq u64, t_capture_ns i64,
width u16, height u16, meta_len u32; then depth float32[H*W] (metres), gray uint8[H*W],
then ``meta_len`` bytes of UTF-8 JSON.  The sim vehicle writes it, the runtime's ``sim`` camera
source reads it; both use these functions so the format lives in one place.
"""

from __future__ import annotations

import json
import struct

import numpy as np

from .frame import Frame

MAGIC = b"CMNF"
WIRE_VERSION = 1
HEADER = struct.Struct("<4sIQqHHI")
MAX_PIXELS = 1920 * 1080
MAX_META_BYTES = 64 * 1024


class FrameDecodeError(ValueError):
    """Bytes on the camera link are not a frame of this format."""


def encode_frame(frame: Frame) -> bytes:
    depth = np.ascontiguousarray(frame.depth_m, dtype=np.float32)
    gray = np.ascontiguousarray(frame.gray_u8, dtype=np.uint8)
    if depth.ndim != 2 or gray.shape != depth.shape:
        raise ValueError(f"depth {depth.shape} and gray {gray.shape} must be the same (H, W)")
    meta = json.dumps(frame.meta, separators=(",", ":")).encode()
    height, width = depth.shape
    header = HEADER.pack(MAGIC, WIRE_VERSION, frame.seq, frame.t_capture_ns, width, height, len(meta))
    return header + depth.tobytes() + gray.tobytes() + meta


def decode_header(header: bytes) -> tuple[int, int, int, int, int]:
    """-> (seq, t_capture_ns, width, height, meta_len); the payload length follows from them."""
    if len(header) != HEADER.size:
        raise FrameDecodeError(f"short header: {len(header)} of {HEADER.size} bytes")
    magic, version, seq, t_ns, width, height, meta_len = HEADER.unpack(header)
    if magic != MAGIC:
        raise FrameDecodeError(f"bad magic {magic!r} (expected {MAGIC!r}): the peer is not a cmnav sim camera")
    if version != WIRE_VERSION:
        raise FrameDecodeError(f"camera link version {version}, this runtime speaks {WIRE_VERSION}: update both")
    if not (0 < width * height <= MAX_PIXELS) or meta_len > MAX_META_BYTES:
        raise FrameDecodeError(f"implausible frame {width}x{height} with {meta_len} meta bytes")
    return seq, t_ns, width, height, meta_len


def payload_size(width: int, height: int, meta_len: int) -> int:
    return width * height * 5 + meta_len


def decode_payload(seq: int, t_ns: int, width: int, height: int, payload: bytes, t_received_ns: int | None = None) -> Frame:
    n = width * height
    depth = np.frombuffer(payload, dtype=np.float32, count=n).reshape(height, width)
    gray = np.frombuffer(payload, dtype=np.uint8, count=n, offset=4 * n).reshape(height, width)
    try:
        meta = json.loads(payload[5 * n :].decode()) if len(payload) > 5 * n else {}
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise FrameDecodeError(f"frame {seq}: bad meta JSON ({err})") from err
    return Frame(t_capture_ns=t_ns, depth_m=depth, gray_u8=gray, seq=seq, meta=meta, t_received_ns=t_received_ns)
