"""The numpy PNG reader/writer agrees with OpenCV both ways: every row filter cv2 writes, gray,
BGR and BGRA, and the errors name the file."""

import struct
import zlib

import cv2
import numpy as np
import pytest

from training.data import pngio
from training.data.pngio import PngError, decode_png, encode_png

FILTERS = {
    "none": cv2.IMWRITE_PNG_FILTER_NONE,
    "sub": cv2.IMWRITE_PNG_FILTER_SUB,
    "up": cv2.IMWRITE_PNG_FILTER_UP,
    "average": cv2.IMWRITE_PNG_FILTER_AVG,
    "paeth": cv2.IMWRITE_PNG_FILTER_PAETH,
    "adaptive": cv2.IMWRITE_PNG_ALL_FILTERS,
}


def _image(channels: int, seed: int = 0, height: int = 37, width: int = 53) -> np.ndarray:
    """Smooth shading plus noise, so every filter has something to predict (and wraps mod 256)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    planes = [
        128 + 90 * np.sin(xx / (5.0 + c) + c) * np.cos(yy / (7.0 + c)) + rng.normal(0, 20, (height, width))
        for c in range(channels)
    ]
    image = np.stack(planes, axis=-1).clip(0, 255).astype(np.uint8)
    return image[..., 0] if channels == 1 else image


def _filter_types(data: bytes) -> set[int]:
    """The row filter bytes actually used in a PNG (to know the test exercises each one)."""
    pos, idat = 8, b""
    while True:
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            width, height, _, color_type = struct.unpack(">IIBB", body[:10])
        elif kind == b"IDAT":
            idat += body
        elif kind == b"IEND":
            break
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[color_type]
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(height, 1 + width * channels)
    return set(rows[:, 0].tolist())


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("filter_name", list(FILTERS))
def test_reads_what_opencv_writes(channels, filter_name):
    image = _image(channels, seed=channels)
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_FILTER, FILTERS[filter_name]])
    assert ok
    data = buf.tobytes()
    expected = {"none": {0}, "sub": {1}, "up": {2}, "average": {3}, "paeth": {4}}.get(filter_name)
    if expected is not None:  # row 0 may get another filter from libpng; the rest must not
        assert expected <= _filter_types(data)
    np.testing.assert_array_equal(decode_png(data), image)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_opencv_reads_what_we_write(channels, tmp_path):
    image = _image(channels, seed=10 + channels, height=64, width=31)
    path = tmp_path / "ours.png"
    path.write_bytes(encode_png(image))
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, image)  # BGR(A) in memory on both sides
    np.testing.assert_array_equal(decode_png(path.read_bytes()), image)


def test_channel_order_is_opencvs():
    bgr = np.zeros((2, 2, 3), np.uint8)
    bgr[..., 0] = 255  # pure blue
    rgb_in_file = decode_png(cv2.imencode(".png", bgr)[1].tobytes())
    assert rgb_in_file[0, 0].tolist() == [255, 0, 0]
    assert cv2.imdecode(np.frombuffer(encode_png(bgr), np.uint8), cv2.IMREAD_COLOR)[0, 0].tolist() == [255, 0, 0]


def test_gray_alpha_reads_as_bgra_like_opencv(tmp_path):
    gray_alpha = np.stack([_image(1, seed=5), _image(1, seed=6)], axis=-1)
    height, width = gray_alpha.shape[:2]
    raw = np.concatenate([np.zeros((height, 1), np.uint8), gray_alpha.reshape(height, -1)], axis=1)  # filter None
    data = (
        pngio.SIGNATURE
        + pngio._chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 4, 0, 0, 0))
        + pngio._chunk(b"IDAT", zlib.compress(raw.tobytes()))
        + pngio._chunk(b"IEND", b"")
    )
    path = tmp_path / "ga.png"
    path.write_bytes(data)
    np.testing.assert_array_equal(decode_png(data), cv2.imread(str(path), cv2.IMREAD_UNCHANGED))


def test_read_and_write_without_opencv(monkeypatch, tmp_path):
    monkeypatch.setattr(pngio, "opencv", lambda: None)
    image = _image(3, seed=7)
    pngio.write_png(tmp_path / "a.png", image)
    np.testing.assert_array_equal(pngio.read_png(tmp_path / "a.png"), image)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED), image)
    with pytest.raises(PngError, match="missing.png"):
        pngio.read_png(tmp_path / "missing.png")


def test_unsupported_and_corrupt_files_are_named():
    interlaced = cv2.imencode(".png", _image(1))[1].tobytes()
    header = struct.pack(">IIBBBBB", 53, 37, 8, 0, 0, 0, 1)
    interlaced = interlaced[:8] + pngio._chunk(b"IHDR", header) + interlaced[8 + 25 :]
    with pytest.raises(PngError, match=r"x\.png is an interlaced .*opencv-python-headless"):
        decode_png(interlaced, "x.png")
    sixteen = cv2.imencode(".png", _image(1).astype(np.uint16) * 257)[1].tobytes()
    with pytest.raises(PngError, match=r"d\.png is a 16-bit PNG"):
        decode_png(sixteen, "d.png")
    good = encode_png(_image(1))
    with pytest.raises(PngError, match=r"c\.png is corrupt \(CRC"):
        decode_png(good[:45] + bytes([good[45] ^ 1]) + good[46:], "c.png")
    with pytest.raises(PngError, match=r"t\.png is truncated"):
        decode_png(good[:-20], "t.png")
    with pytest.raises(PngError, match=r"j\.jpg is not a PNG"):
        decode_png(cv2.imencode(".jpg", _image(3))[1].tobytes(), "j.jpg")
