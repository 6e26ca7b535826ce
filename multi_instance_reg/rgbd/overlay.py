"""The debug picture of one frame: matched keypoints coloured by instance, each instance's
box projected into the image with its id. No ROS; the node publishes it, tools save it."""
from __future__ import annotations

import cv2
import numpy as np

from ..messages import CameraIntrinsics
from ..transforms import apply_transform

# Box edges between the corners of ObjectModel.box_corners() (index bits: x, y, z sign).
_EDGES = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]


def project(points_cam: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
    """(N, 3) camera-frame points -> (N, 2) pixels (pinhole; points behind the camera give NaN)."""
    K = intrinsics.K
    z = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * points_cam[:, 0] / z + K[0, 2]
        v = K[1, 1] * points_cam[:, 1] / z + K[1, 2]
    uv = np.stack([u, v], axis=1)
    uv[z <= 1e-6] = np.nan
    return uv


def draw_box(img: np.ndarray, T: np.ndarray, box_corners: np.ndarray, intrinsics: CameraIntrinsics,
             colour, thickness: int = 2, label: str | None = None) -> bool:
    """Draw the box ``box_corners`` (8, 3, model frame) posed by ``T`` (model -> camera) into
    ``img`` in place, with ``label`` above it; False when the box is behind the camera."""
    uv = project(apply_transform(np.asarray(T, dtype=np.float64), box_corners), intrinsics)
    if not np.all(np.isfinite(uv)) or np.abs(uv).max() > 1e5:
        return False
    pts = np.round(uv).astype(np.int32)
    for a, b in _EDGES:
        cv2.line(img, tuple(pts[a]), tuple(pts[b]), colour, thickness, cv2.LINE_AA)
    if label is not None:
        top = pts[np.argmin(pts[:, 1])]
        org = (int(top[0]), int(top[1]) - 6)
        cv2.putText(img, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 4, cv2.LINE_AA)
        cv2.putText(img, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 2, cv2.LINE_AA)
    return True


def draw_points(img: np.ndarray, T: np.ndarray, points: np.ndarray, intrinsics: CameraIntrinsics, colour) -> int:
    """Draw ``points`` (N, 3, model frame) posed by ``T`` as single pixels into ``img`` in
    place (a model's surface shows where a pose puts it better than its box); returns how
    many fell inside the image."""
    uv = project(apply_transform(np.asarray(T, dtype=np.float64), np.asarray(points, np.float64)), intrinsics)
    h, w = img.shape[:2]
    ok = np.all(np.isfinite(uv), axis=1)
    px = np.round(uv[ok]).astype(np.int64)
    px = px[(px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)]
    img[px[:, 1], px[:, 0]] = colour
    return len(px)


def draw_overlay(rgb: np.ndarray, result, intrinsics: CameraIntrinsics, box_corners: np.ndarray,
                 colour_of, instances=None) -> np.ndarray:
    """A copy of ``rgb`` with ``result.keypoints_uv`` as dots coloured by ``result.labels``
    (outliers small and grey) and every instance's box (``box_corners`` (8, 3), model frame)
    drawn in its colour (a dict: each instance's object's corners, by ``object``). ``colour_of(id) -> (r, g, b)``. ``instances`` (tracked ones, keyed by
    their ``track_id``) replace ``result.instances``; ``result`` may then be None (no dots)."""
    out = np.ascontiguousarray(rgb.copy())
    if result is not None:
        labels = np.asarray(result.labels)
        for (u, v), label in zip(np.asarray(result.keypoints_uv), labels):
            inlier = label >= 0
            cv2.circle(out, (int(round(u)), int(round(v))), 3 if inlier else 1, colour_of(int(label)),
                       -1 if inlier else 1, cv2.LINE_AA)
    for inst in result.instances if instances is None else instances:
        key = int(getattr(inst, "track_id", inst.id))
        corners = box_corners[inst.object] if isinstance(box_corners, dict) else box_corners
        draw_box(out, inst.T, corners, intrinsics, colour_of(key), label=str(key))
    return out
