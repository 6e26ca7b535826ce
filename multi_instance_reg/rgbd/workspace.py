"""The workspace: what the user knows about where the objects can be. No ROS.

An oriented box in the camera optical frame (centre, size, roll / pitch / yaw), optionally an
image mask (PNG: non-zero where objects may be), on top of the depth range every front end
already keeps (``frontend.depth_min`` / ``depth_max``). The front ends look for keypoints and
points only inside it (``InstanceRegistration.workspace_pixels``), so nothing is hypothesised
outside it, and a frame costs only what lies inside.

    ws = Workspace.from_config(WorkspaceConfig(size_x=0.6, size_y=0.4, size_z=0.5, centre_z=0.8))
    inside = ws.pixels(depth_m, intrinsics)       # (H, W) bool
    ws.draw(bgr_image, intrinsics)                # the box's edges, in place

A box given in another (TF) frame is not supported yet: the node has no tf2 (NOTES section 3).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InputError
from ..messages import CameraIntrinsics
from ..params import param

_BOX = "metres, camera optical frame (x right, y down, z forward)"


@dataclass(frozen=True)
class WorkspaceConfig:
    """The workspace's parameters (``workspace.*``); all sizes 0 and no mask: no workspace."""
    centre_x: float = param(0.0, f"workspace box centre x, {_BOX}", -100.0, 100.0)
    centre_y: float = param(0.0, f"workspace box centre y, {_BOX}", -100.0, 100.0)
    centre_z: float = param(0.0, f"workspace box centre z, {_BOX}", -100.0, 100.0)
    size_x: float = param(0.0, "workspace box side along its own x axis, metres (0 on all three sides = no box)", 0.0, 100.0)
    size_y: float = param(0.0, "workspace box side along its own y axis, metres", 0.0, 100.0)
    size_z: float = param(0.0, "workspace box side along its own z axis, metres", 0.0, 100.0)
    roll_deg: float = param(0.0, "workspace box orientation: turn about the camera's x axis, degrees (applied first)", -360.0, 360.0)
    pitch_deg: float = param(0.0, "workspace box orientation: turn about the camera's y axis, degrees (second)", -360.0, 360.0)
    yaw_deg: float = param(0.0, "workspace box orientation: turn about the camera's z axis, degrees (last)", -360.0, 360.0)
    mask: str = param("", "workspace image mask: a PNG of the colour image's size, non-zero where objects may be ('' = none)")

    @property
    def has_box(self) -> bool:
        return self.size_x > 0 or self.size_y > 0 or self.size_z > 0

    @property
    def is_set(self) -> bool:
        return self.has_box or bool(self.mask)


class Workspace:
    """Where objects may be: an oriented box (camera frame) and / or an image mask."""

    def __init__(self, T_box: np.ndarray | None = None, size=None, mask: np.ndarray | None = None):
        self.T_box = None if T_box is None else np.asarray(T_box, np.float64)    # box frame -> camera
        self.half = None if size is None else np.asarray(size, np.float64) / 2.0
        if self.half is not None and not np.all(self.half > 0):
            raise InputError(f"workspace box size must be positive on all three sides, got {list(2 * self.half)} "
                             f"(set workspace.size_x, size_y and size_z)")
        self.mask = None if mask is None else np.asarray(mask) > 0

    @staticmethod
    def from_config(config: WorkspaceConfig) -> "Workspace | None":
        """The workspace the parameters describe, or None when they set none."""
        if not config.is_set:
            return None
        T, size = None, None
        if config.has_box:
            T = np.eye(4)
            T[:3, :3] = Rotation.from_euler("xyz", [config.roll_deg, config.pitch_deg, config.yaw_deg],
                                            degrees=True).as_matrix()
            T[:3, 3] = [config.centre_x, config.centre_y, config.centre_z]
            size = [config.size_x, config.size_y, config.size_z]
        return Workspace(T, size, read_mask(config.mask) if config.mask else None)

    def pixels(self, depth_m: np.ndarray, intrinsics: CameraIntrinsics) -> np.ndarray:
        """(H, W) bool: the pixels whose depth puts their point inside the box and that the
        mask allows (pixels without depth: False)."""
        h, w = depth_m.shape
        inside = depth_m > 0
        if self.mask is not None:
            if self.mask.shape != (h, w):
                raise InputError(f"workspace mask is {self.mask.shape[1]}x{self.mask.shape[0]} but the images are "
                                 f"{w}x{h}; draw it on a colour image of the camera")
            inside &= self.mask
        if self.T_box is not None:
            # In the box's frame a pixel's point is z R^T ray - R^T c: per pixel three
            # multiply-adds on rays turned once per camera (float32: 2-3 ms a VGA frame).
            turned, offset = self._turned_rays(intrinsics)
            z = depth_m.astype(np.float32, copy=False)
            for axis in range(3):
                inside &= np.abs(z * turned[axis] - offset[axis]) <= np.float32(self.half[axis])
        return inside

    def _turned_rays(self, intrinsics: CameraIntrinsics):
        """((3, H, W) float32 each pixel's ray (x, y, 1) in the box's axes, (3,) the box
        centre in them), kept per camera."""
        key = (intrinsics.width, intrinsics.height, tuple(np.asarray(intrinsics.K, np.float64).ravel()))
        if getattr(self, "_rays_key", None) != key:
            K = intrinsics.K
            v, u = np.mgrid[0:intrinsics.height, 0:intrinsics.width]
            rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)])
            R = self.T_box[:3, :3]
            self._rays = np.einsum("ij,jhw->ihw", R.T, rays).astype(np.float32)
            self._offset = (R.T @ self.T_box[:3, 3]).astype(np.float32)
            self._rays_key = key
        return self._rays, self._offset

    def corners(self) -> np.ndarray:
        """(8, 3) the box's corners in its own frame, in ``ObjectModel.box_corners``' order."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
        return signs * self.half

    def draw(self, img: np.ndarray, intrinsics: CameraIntrinsics, colour=(255, 160, 0)) -> np.ndarray:
        """The box's edges (where in front of the camera) and the mask's outline drawn into
        ``img`` in place; returns it."""
        from .overlay import draw_box

        if self.mask is not None and self.mask.shape == img.shape[:2]:
            outline, _ = cv2.findContours(self.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(img, outline, -1, colour, 1, cv2.LINE_AA)
        if self.T_box is not None:
            draw_box(img, self.T_box, self.corners(), intrinsics, colour, thickness=1, label="workspace")
        return img


def read_mask(path) -> np.ndarray:
    """(H, W) bool from a PNG (any channel count: non-zero anywhere = allowed)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"workspace mask {path} does not exist (workspace.mask: a PNG, non-zero where objects may be)")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"workspace mask {path} is not a readable image (workspace.mask wants a PNG)")
    out = img.reshape(img.shape[0], img.shape[1], -1).max(axis=2) > 0
    if not out.any():
        raise InputError(f"workspace mask {path} allows no pixel (it is all zero); objects could be found nowhere")
    return out


__all__ = ["WorkspaceConfig", "Workspace", "read_mask"]
