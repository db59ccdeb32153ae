"""Frame image payloads: the encodings a Frame may carry, to numpy grey images."""
from __future__ import annotations

import cv2
import numpy as np

from protocol.codec import ProtocolError
from protocol.messages import RAW_CHANNELS, Frame
from toptag.images import decode_gray
from toptag.inputs import InputError

_GRAY_FROM = {"bgr8": cv2.COLOR_BGR2GRAY, "rgb8": cv2.COLOR_RGB2GRAY}


def frame_to_gray(frame: Frame) -> np.ndarray:
    """The frame's image as a 2-D uint8 array of the frame's size; ProtocolError (reason 'frame') if the
    bytes do not decode or do not match the header."""
    if frame.encoding in RAW_CHANNELS:
        ch = RAW_CHANNELS[frame.encoding]
        img = np.frombuffer(frame.image, np.uint8).reshape(frame.height, frame.width, ch)
        return img[:, :, 0].copy() if ch == 1 else cv2.cvtColor(img, _GRAY_FROM[frame.encoding])
    try:
        img = decode_gray(frame.image, f"frame {frame.seq} of {frame.rsu_id}")
    except InputError as e:
        raise ProtocolError(str(e), reason="frame", msg_type="Frame") from None
    if img.shape != (frame.height, frame.width):
        raise ProtocolError(f"frame {frame.seq} of {frame.rsu_id}: image is {img.shape[1]}x{img.shape[0]}, "
                            f"header says {frame.width}x{frame.height}", reason="frame", msg_type="Frame")
    return img
