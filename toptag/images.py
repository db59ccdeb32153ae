"""Reading camera images with a clear one-line error for missing, corrupt or mismatched files."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from toptag.inputs import InputError

_TRAILERS = {b"\xff\xd8": b"\xff\xd9", b"\x89PNG": b"IEND\xaeB`\x82"}


def decode_gray(data: bytes, what: str) -> np.ndarray:
    """Decode JPEG/PNG/other bytes to a 2-D uint8 image, refusing truncated or undecodable data."""
    if not data:
        raise InputError(f"{what}: empty file")
    for magic, trailer in _TRAILERS.items():
        # libjpeg/libpng decode a truncated file silently into a grey-filled image: refuse it.
        if data.startswith(magic) and trailer not in data[-64:]:
            raise InputError(f"{what}: corrupt or truncated image data")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError(f"{what}: not a readable image")
    return img


def read_gray(path: str | Path, expected_size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image file as grayscale; `expected_size` = (width, height) of the camera that took it."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise InputError(f"image {p}: no such file") from None
    except OSError as e:
        raise InputError(f"image {p}: cannot read ({e.strerror or e})") from None
    img = decode_gray(data, f"image {p}")
    if expected_size is not None and (img.shape[1], img.shape[0]) != tuple(expected_size):
        raise InputError(f"image {p}: size {img.shape[1]}x{img.shape[0]} does not match the camera's "
                         f"{expected_size[0]}x{expected_size[1]}")
    return img
