"""Printed AprilTag patterns (SPEC.md: tag orientation).

`tag_cells(family, id)` is the official family image at one pixel per cell: the black square with its
data bits plus the one-cell white border (10x10 for tag36h11), row 0 = printed top, column 0 = printed
left, 0 = black, 255 = white. It comes from OpenCV's DICT_APRILTAG_* dictionaries, whose
`generateImageMarker` output is the official image turned by 180 degrees (turned back here).
"""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from toptag.vehicle import FAMILY_BITS

_CV_DICTS = {
    "tag36h11": cv2.aruco.DICT_APRILTAG_36h11,
    "tag25h9": cv2.aruco.DICT_APRILTAG_25h9,
    "tag16h5": cv2.aruco.DICT_APRILTAG_16h5,
}


def grid_size(family: str) -> int:
    """Cells per side of the printed plate: data bits + black border (2) + white border (2)."""
    if family not in FAMILY_BITS:
        raise ValueError(f"unknown tag family {family!r} (known: {', '.join(FAMILY_BITS)})")
    return FAMILY_BITS[family] + 4


@lru_cache(maxsize=None)
def family_size(family: str) -> int:
    """Number of ids in the family."""
    grid_size(family)
    return int(cv2.aruco.getPredefinedDictionary(_CV_DICTS[family]).bytesList.shape[0])


@lru_cache(maxsize=4096)
def tag_cells(family: str, tag_id: int) -> np.ndarray:
    """(N, N) uint8 cell image of one tag, white border included, official orientation (read-only)."""
    n = grid_size(family)
    if not 0 <= int(tag_id) < family_size(family):
        raise ValueError(f"{family} has no id {tag_id} (ids 0..{family_size(family) - 1})")
    d = cv2.aruco.getPredefinedDictionary(_CV_DICTS[family])
    m = cv2.aruco.generateImageMarker(d, int(tag_id), n - 2, borderBits=1)
    m = np.rot90(np.pad(m, 1, constant_values=255), 2)
    m = np.ascontiguousarray(np.where(m > 127, 255, 0).astype(np.uint8))
    m.setflags(write=False)
    return m
