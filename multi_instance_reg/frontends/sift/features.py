"""SIFT keypoints and descriptors of a colour image (OpenCV)."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SiftSettings:
    nfeatures: int = 0                 # 0 = keep all
    contrast_threshold: float = 0.02   # OpenCV default 0.04
    edge_threshold: float = 10.0
    upsample: float = 1.0              # image scale before SIFT: > 1 more keypoints on small objects, < 1 faster
    octave_layers: int = 3             # scales per octave (Lowe: 3)


_DETECTORS: dict[SiftSettings, cv2.SIFT] = {}


def _detector(settings: SiftSettings):
    det = _DETECTORS.get(settings)
    if det is None:
        det = cv2.SIFT_create(nfeatures=settings.nfeatures, nOctaveLayers=settings.octave_layers,
                              contrastThreshold=settings.contrast_threshold, edgeThreshold=settings.edge_threshold)
        _DETECTORS[settings] = det
    return det


def to_gray(rgb: np.ndarray) -> np.ndarray:
    return rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def extract_sift(rgb: np.ndarray, settings: SiftSettings = SiftSettings(),
                 mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """SIFT on an (H, W, 3) RGB or (H, W) grey uint8 image.

    Returns (uv (K, 2) float32 pixel coordinates in the input image, descriptors (K, 128) float32).
    ``mask`` (H, W) bool/uint8 restricts detection to nonzero pixels.
    """
    gray = to_gray(rgb)
    s = float(settings.upsample)
    if s != 1.0:
        gray = cv2.resize(gray, None, fx=s, fy=s, interpolation=cv2.INTER_LINEAR if s > 1 else cv2.INTER_AREA)
        if mask is not None:
            mask = cv2.resize(mask.astype(np.uint8), None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST)
    m = None if mask is None else (mask > 0).astype(np.uint8)
    kps, desc = _detector(settings).detectAndCompute(gray, m)
    if desc is None or not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    uv = np.array([k.pt for k in kps], dtype=np.float32)
    if s != 1.0:
        # Pixel centres: x_small = (x_big + 0.5) / s - 0.5 for cv2.resize's half-pixel convention.
        uv = (uv + 0.5) / s - 0.5
    return uv, desc.astype(np.float32, copy=False)


def extract_sift_in_region(rgb: np.ndarray, mask: np.ndarray, settings: SiftSettings = SiftSettings(),
                           margin: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints inside ``mask`` (H, W, nonzero = search here), computed on the bounding
    box of the mask plus ``margin`` pixels only: the Gaussian pyramid, SIFT's main cost, is
    built for that crop. Returns (uv (K, 2) float32 full-image pixels, (K, 128) float32)."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    h, w = mask.shape
    x0, x1 = max(int(xs.min()) - margin, 0), min(int(xs.max()) + margin + 1, w)
    y0, y1 = max(int(ys.min()) - margin, 0), min(int(ys.max()) + margin + 1, h)
    uv, desc = extract_sift(rgb[y0:y1, x0:x1], settings, mask[y0:y1, x0:x1])
    if len(uv):
        uv = uv + np.array([x0, y0], np.float32)
    return uv, desc
