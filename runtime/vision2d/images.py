"""Image conversions shared by the 2D competences."""

from __future__ import annotations

import cv2
import numpy as np


def to_grey(image: np.ndarray, require_uint8: bool = False) -> np.ndarray:
    """(H, W) grey of an (H, W) grey or (H, W, 3) RGB image, in the image's own dtype.

    require_uint8 : refuse anything but 8-bit images (what Sequence.frames gives), for code
    whose thresholds are in 8-bit grey levels."""
    image = np.asarray(image)
    if require_uint8 and image.dtype != np.uint8:
        raise ValueError(f"image has dtype {image.dtype}; pass 8-bit images (as Sequence.frames gives)")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    raise ValueError(f"image has shape {image.shape}; pass (H, W) grey or (H, W, 3) RGB")
