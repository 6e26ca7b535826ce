"""PNG previews of rendered frames, so a person can look at what was made: the colour image,
the depth colourised (invalid = black), and the ground-truth boxes drawn over the colour."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

_BOX_EDGES = [(0, 1), (1, 3), (3, 2), (2, 0), (4, 5), (5, 7), (7, 6), (6, 4), (0, 4), (1, 5), (2, 6), (3, 7)]


def colourise_depth(depth_mm: np.ndarray, near_mm: float = 300.0, far_mm: float = 2000.0) -> np.ndarray:
    """BGR image of a 16UC1 depth map (turbo colour map, 0 = black)."""
    d = np.clip((depth_mm.astype(np.float32) - near_mm) / (far_mm - near_mm), 0, 1)
    img = cv2.applyColorMap((255 * (1 - d)).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[depth_mm == 0] = 0
    return img


def colour_and_depth(frame, far_mm: float = 3500.0) -> np.ndarray:
    """BGR image of a RenderedFrame's colour beside its colourised depth (0.3 m to ``far_mm``):
    the form of the docs' figures and of a real camera's frames put side by side."""
    return np.concatenate([cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR),
                           colourise_depth(frame.depth_mm, 300.0, far_mm)], axis=1)


def box_corners(dimensions_m) -> np.ndarray:
    """The 8 corners (object frame) of an object's bounding box, index bits = (x, y, z) signs."""
    h = 0.5 * np.asarray(dimensions_m, dtype=np.float64)
    return np.array([[sx * h[0], sy * h[1], sz * h[2]] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])


def draw_ground_truth(rgb: np.ndarray, K: np.ndarray, poses: np.ndarray, dimensions_m,
                      visibility=None) -> np.ndarray:
    """BGR copy of ``rgb`` with each instance's box as a wireframe and its index."""
    img = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    corners = box_corners(dimensions_m)
    for k, T in enumerate(poses):
        pc = corners @ T[:3, :3].T + T[:3, 3]
        if np.any(pc[:, 2] < 0.05):
            continue
        uv = pc @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        colour = tuple(int(c) for c in cv2.applyColorMap(np.uint8([[37 * k % 256]]), cv2.COLORMAP_HSV)[0, 0])
        for a, b in _BOX_EDGES:
            pa = tuple(int(round(v)) for v in uv[a])
            pb = tuple(int(round(v)) for v in uv[b])
            cv2.line(img, pa, pb, colour, 1, cv2.LINE_AA)
        # Object x axis (red) and z axis (blue) from the centre: shows the frame, not just the box.
        c = T[:3, 3] @ K.T
        for axis, col in ((0, (0, 0, 255)), (2, (255, 0, 0))):
            tip = (T[:3, 3] + 0.5 * corners.max(0)[axis] * T[:3, axis]) @ K.T
            cv2.line(img, (int(c[0] / c[2]), int(c[1] / c[2])), (int(tip[0] / tip[2]), int(tip[1] / tip[2])),
                     col, 2, cv2.LINE_AA)
        text = f"{k}" if visibility is None else f"{k}:{int(round(100 * visibility[k]))}%"
        cv2.putText(img, text, (int(c[0] / c[2]) + 4, int(c[1] / c[2]) - 4), cv2.FONT_HERSHEY_SIMPLEX,
                    0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def write_preview(directory, frame, scene) -> list[Path]:
    """Write colour, depth and ground-truth PNGs of one RenderedFrame; returns their paths."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    stem = f"{scene.kind}_{frame.index:04d}"
    paths = [directory / f"{stem}_colour.png", directory / f"{stem}_depth.png", directory / f"{stem}_truth.png"]
    cv2.imwrite(str(paths[0]), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    # A room behind the table (background "clutter") lies 2.5-4 m away: show it in colour too.
    far_mm = 4000.0 if getattr(scene, "background", "wall") == "clutter" else 2000.0
    cv2.imwrite(str(paths[1]), colourise_depth(frame.depth_mm, far_mm=far_mm))
    cv2.imwrite(str(paths[2]), draw_ground_truth(frame.rgb, frame.K, frame.poses, scene.target.dimensions_m,
                                                 frame.visibility))
    return paths
