"""A self-made RGB-D test scene without the synthetic renderer: textured rectangles (a
scikit-image picture) on planes at known poses, warped with their exact homography, and the
exact planar depth map. Used where a test needs a frame with known geometry."""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from multi_instance_reg.messages import CameraIntrinsics
from multi_instance_reg.transforms import make_transform

K = np.array([[379.05, 0, 321.89], [0, 378.68, 238.97], [0, 0, 1.0]])
INTRINSICS = CameraIntrinsics(K=K, width=640, height=480)


def render_planes(texture: np.ndarray, size_m, poses, rgb=None, depth=None, K=K, width=640, height=480):
    """Draw ``texture`` as a size_m = (sx, sy) rectangle centred at each pose's origin, in the
    pose's z = 0 plane, over (rgb, depth). Returns (rgb uint8, depth float32 metres, 0 = none)."""
    th, tw = texture.shape[:2]
    rgb = np.zeros((height, width, 3), np.uint8) if rgb is None else rgb.copy()
    depth = np.zeros((height, width), np.float32) if depth is None else depth.copy()
    S = np.array([[size_m[0] / tw, 0, -size_m[0] / 2], [0, size_m[1] / th, -size_m[1] / 2], [0, 0, 1]])
    uu, vv = np.meshgrid(np.arange(width), np.arange(height))
    rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones(uu.shape)], -1)
    for T in poses:
        H = K @ np.column_stack([T[:3, 0], T[:3, 1], T[:3, 3]]) @ S
        warped = cv2.warpPerspective(texture, H, (width, height), flags=cv2.INTER_LINEAR)
        inside = cv2.warpPerspective(np.ones((th, tw), np.uint8), H, (width, height), flags=cv2.INTER_NEAREST) > 0
        n = T[:3, 2]
        z = (n @ T[:3, 3]) / (rays @ n)
        front = inside & (z > 0) & ((depth == 0) | (z < depth))
        rgb[front] = warped[front]
        depth[front] = z[front]
    return rgb, depth


def card_pose(rx=0.0, ry=0.0, rz=0.0, t=(0.0, 0.0, 0.6)) -> np.ndarray:
    return make_transform(Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix(), t)


def table(rng, size_m=3.0, z=1.0):
    """A big, weakly textured plane facing the camera at distance z, filling the view."""
    tex = cv2.GaussianBlur(rng.integers(70, 130, (300, 300, 3)).astype(np.uint8), (0, 0), 2)
    return render_planes(tex, (size_m, size_m), [card_pose(t=(0, 0, z))])
