"""Calibration boards (ChArUco and chessboard): the board file, its printed pattern and its detection
with OpenCV.

Board file (JSON), sizes in metres as printed (measure them: the print scale is the focal length's):

    {"type": "charuco", "squares_x": 12, "squares_y": 9, "square_size": 0.06, "marker_size": 0.045,
     "dictionary": "DICT_4X4_100"}
    {"type": "chessboard", "squares_x": 10, "squares_y": 7, "square_size": 0.025}

Board coordinates: origin at the outer top-left corner of the squares, x along squares_x, y along
squares_y, z = 0 on the board. A ChArUco board's corners are its inner chessboard corners, found
from the markers (so a partly visible board still counts, which is how the image corners get covered);
a chessboard's (squares_x − 1) × (squares_y − 1) inner corners must all be visible.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from toptag.inputs import read_model

MARKER_BITS = {"4X4": 4, "5X5": 5, "6X6": 6, "7X7": 7}
# The board README recommends a site to print (A0 on a rigid plate; why: README "Calibration accuracy").
RECOMMENDED_BOARD = "board_charuco_a0.json"


def recommended_board_path() -> Path:
    """The board file shipped with toptag (toptag/data/board_charuco_a0.json)."""
    from importlib import resources

    return Path(str(resources.files("toptag.data").joinpath(RECOMMENDED_BOARD)))


class BoardFile(BaseModel):
    model_config = ConfigDict(extra="forbid")

    type: Literal["charuco", "chessboard"]
    squares_x: int = Field(ge=3, le=100)
    squares_y: int = Field(ge=3, le=100)
    square_size: float = Field(gt=0, description="edge of one square, m")
    marker_size: float | None = Field(default=None, gt=0, description="ChArUco marker edge, m")
    dictionary: str = "DICT_4X4_100"

    @model_validator(mode="after")
    def _consistent(self) -> "BoardFile":
        if self.type == "charuco":
            if self.marker_size is None:
                raise ValueError("marker_size: required for a charuco board")
            if self.marker_size >= self.square_size:
                raise ValueError("marker_size: must be smaller than square_size")
            if not hasattr(cv2.aruco, self.dictionary) or not self.dictionary.startswith("DICT_"):
                raise ValueError(f"dictionary: unknown OpenCV ArUco dictionary {self.dictionary!r}")
            n_markers = (self.squares_x * self.squares_y) // 2
            if n_markers > cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList.shape[0]:
                raise ValueError(f"dictionary: {self.dictionary} has fewer than the board's {n_markers} markers")
        return self


@dataclass
class BoardView:
    """The board corners found in one image."""

    ids: np.ndarray  # (N,) corner ids (index into Board.object_points)
    image_points: np.ndarray  # (N, 2) pixels, OpenCV convention
    object_points: np.ndarray  # (N, 3) board coordinates, m
    name: str = ""


class Board:
    def __init__(self, spec: BoardFile):
        self.spec = spec

    @classmethod
    def load(cls, path: str | Path) -> "Board":
        return cls(read_model(BoardFile, path, "board file"))

    @classmethod
    def from_dict(cls, data: dict) -> "Board":
        return cls(BoardFile.model_validate(data))

    @property
    def inner(self) -> tuple[int, int]:
        """Inner corners per row and per column."""
        return self.spec.squares_x - 1, self.spec.squares_y - 1

    @cached_property
    def object_points(self) -> np.ndarray:
        """(N, 3) board coordinates of every inner corner, id order (row by row, x fastest)."""
        nx, ny = self.inner
        s = self.spec.square_size
        j, i = np.mgrid[0:ny, 0:nx]
        return np.column_stack([(i.ravel() + 1) * s, (j.ravel() + 1) * s, np.zeros(nx * ny)])

    @cached_property
    def _charuco(self):
        s = self.spec
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, s.dictionary))
        return cv2.aruco.CharucoBoard((s.squares_x, s.squares_y), s.square_size, s.marker_size, d)

    @cached_property
    def _charuco_detector(self):
        # tryRefineMarkers: markers missed at first (small, tilted, smeared by the stream's codec) are
        # looked for again where the board's layout puts them: on rendered H.264 views of a tilted board
        # about 1.2-1.4 times the corners (corner noise unchanged), and the information with them.
        params = cv2.aruco.CharucoParameters()
        params.tryRefineMarkers = True
        return cv2.aruco.CharucoDetector(self._charuco, params)

    def pattern(self) -> tuple[np.ndarray, float, int]:
        """(uint8 image, texel size m, margin texels): the printed board, one white square of margin
        around it, at a resolution where every marker cell is whole texels (exact rendering)."""
        s = self.spec
        k = 1
        if s.type == "charuco":
            bits = MARKER_BITS.get(s.dictionary.split("_")[1], 4) + 2
            k = next((k for k in range(4, 400) if _whole(k * s.marker_size / s.square_size / bits)
                      and _whole(k * (s.square_size - s.marker_size) / s.square_size / 2)), 200)
            size = (s.squares_x * k + 2 * k, s.squares_y * k + 2 * k)
            img = self._charuco.generateImage(size, marginSize=k, borderBits=1)
        else:
            j, i = np.mgrid[0:s.squares_y, 0:s.squares_x]
            img = np.pad(np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8), 1, constant_values=255)
        return img, s.square_size / k, k

    def printable(self, dpi: float = 200.0, margin: float = 0.01) -> tuple[np.ndarray, float]:
        """(uint8 image, pixels per metre): the board to print at 100 % scale, `margin` metres of white
        around the squares; a whole number of pixels per square, so that the corners are exact and the
        printed scale is the file's (pixels per metre, also in the PNG written by write_png)."""
        s = self.spec
        px = max(8, round(s.square_size / 0.0254 * dpi))
        border = round(margin / s.square_size * px)
        size = (s.squares_x * px + 2 * border, s.squares_y * px + 2 * border)
        if s.type == "charuco":
            img = self._charuco.generateImage(size, marginSize=border, borderBits=1)
        else:
            j, i = np.mgrid[0:s.squares_y, 0:s.squares_x]
            squares = np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8).repeat(px, axis=0).repeat(px, axis=1)
            img = np.pad(squares, border, constant_values=255)
        return img, px / s.square_size

    def detect(self, gray: np.ndarray, name: str = "") -> BoardView | None:
        """The board's corners in a gray image (None if the board is not found)."""
        if self.spec.type == "charuco":
            corners, ids, _, _ = self._charuco_detector.detectBoard(gray)
            if ids is None or len(ids) < 4:
                return None
            ids = ids.ravel().astype(int)
            pts = corners.reshape(-1, 2).astype(float)
        else:
            flags = cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
            ok, corners = cv2.findChessboardCornersSB(gray, self.inner, flags=flags)
            if not ok:
                return None
            ids = np.arange(len(corners))
            pts = corners.reshape(-1, 2).astype(float)
        return BoardView(ids, pts, self.object_points[ids], name)


def write_png(path: str | Path, image: np.ndarray, pixels_per_metre: float) -> None:
    """A PNG with its print scale (pHYs chunk), so that printing it at 100 % gives the board's size."""
    import struct
    import zlib

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError("PNG encoding failed")
    data = struct.pack(">IIB", round(pixels_per_metre), round(pixels_per_metre), 1)
    chunk = struct.pack(">I", len(data)) + b"pHYs" + data + struct.pack(">I", zlib.crc32(b"pHYs" + data))
    raw = buf.tobytes()
    end_ihdr = 8 + 8 + 13 + 4  # signature, IHDR length and type, its 13 bytes, its CRC
    Path(path).write_bytes(raw[:end_ihdr] + chunk + raw[end_ihdr:])


def _whole(x: float) -> bool:
    return abs(x - round(x)) < 1e-9 and round(x) >= 1
