"""What a RealSense D455 makes of a rendered scene: intrinsics, colour and depth noise.

Colour: mild optical blur, vignetting, then shot + read noise, rgb8.
Depth (aligned to colour, 16UC1 millimetres, 0 = no measurement):
- noise sigma_z = DEPTH_NOISE_PER_M * z^2 (z in metres), about 1.8 mm at 1 m and 7 mm at 2 m,
  the quadratic growth of a stereo camera's error (29 mm at 4 m, under the 2 % at 4 m
  that the D455 data sheet allows); independent per pixel by default, or, with
  ``correlation_px``, shared by neighbouring pixels (a stereo matcher finds each disparity
  over a window of pixels, so real surfaces come out wavy rather than speckled): the same
  sigma_z per pixel, smooth over about that many pixels;
- 0 at depth discontinuities (3x3 depth spread above 2.5 % of the depth), in the stereo
  occlusion shadow left of foreground edges (95 mm baseline), in random small dropout blobs
  (~2 % of pixels) and outside the range [MIN_RANGE_M, MAX_RANGE_M].
The images are rendered without lens distortion, so camera_info says plumb_bob with all
five coefficients 0.

Sensor profiles (``SensorProfile``, ``sensor_profile(name, seed, randomise)``): "d455" is the
model above, unchanged; "realistic" adds what real depth cameras do and the model above
lacks (NOTES section 15): noise sigma_z = 0.004 z^2 + 0.5 mm (the model of the other renderer
the project is checked against), 70 % of the depth-edge pixels dropped instead of all, and a
share of the rest "flying" (a depth between the foreground's and the background's), 1.5 %
isolated single-pixel dropouts anywhere, and depth quantised as disparity steps (1/20 px of
a 382 px depth imager: 1.4 mm at 1 m, 5.5 mm at 2 m). ``randomise`` draws each of these per
seed from a range around the realistic value (``PROFILE_RANGES``).
"""
from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from ..errors import InputError
from ..messages import CameraIntrinsics

DEPTH_NOISE_PER_M = 0.0018     # sigma_z [m] = DEPTH_NOISE_PER_M * z[m]^2
MIN_RANGE_M = 0.3
MAX_RANGE_M = 6.0
STEREO_BASELINE_M = 0.095
EDGE_SPREAD_REL = 0.025        # 3x3 depth spread / depth above which a pixel is invalid
DROPOUT_THRESHOLD = 0.97       # of a smoothed uniform field: ~2 % of pixels in blobs of ~8 px

RESOLUTIONS = ("640x480", "1280x720")
# Disparity is quantised on the depth imager, whatever the colour resolution: a D455's depth
# stream at 640x480 has fx of about 382 px (95 mm baseline).
DEPTH_IMAGER_FX_PX = 382.0


@dataclass(frozen=True)
class SensorProfile:
    """What the depth of a profile does beyond the noise-free render (see the module
    docstring); the "d455" values reproduce ``simulate_depth`` without a profile exactly."""
    name: str = "d455"
    noise_per_m: float = DEPTH_NOISE_PER_M      # sigma_z = noise_per_m * z^2 + noise_floor_m
    noise_floor_m: float = 0.0
    edge_dropout: float = 1.0                   # share of depth-edge pixels without depth
    flying: float = 0.0                         # share of the other edge pixels given a depth in between
    speckle: float = 0.0                        # share of isolated single-pixel dropouts
    disparity_step_px: float = 0.0              # quantisation of disparity (0: none beyond 1 mm)

    def description(self) -> dict:
        return {k: (round(v, 6) if isinstance(v, float) else v) for k, v in asdict(self).items()}


SENSOR_PROFILES = {
    "d455": SensorProfile(),
    "realistic": SensorProfile("realistic", noise_per_m=0.004, noise_floor_m=0.0005, edge_dropout=0.7,
                               flying=0.5, speckle=0.015, disparity_step_px=0.05),
}
# randomise=True: each drawn per seed, uniformly in these ranges (the realistic value inside).
PROFILE_RANGES = {"noise_per_m": (0.0018, 0.006), "noise_floor_m": (0.0, 0.001), "edge_dropout": (0.5, 0.9),
                  "flying": (0.2, 0.8), "speckle": (0.005, 0.025), "disparity_step_px": (1 / 32, 1 / 8)}


def sensor_profile(name: str = "d455", seed: int = 0, randomise: bool = False) -> SensorProfile:
    """The named profile, or with ``randomise`` one drawn from ``PROFILE_RANGES`` by ``seed``
    (named "<name>-random"). InputError for an unknown name."""
    if name not in SENSOR_PROFILES:
        raise InputError(f"unknown sensor profile '{name}'; choose one of: {', '.join(SENSOR_PROFILES)}")
    if not randomise:
        return SENSOR_PROFILES[name]
    rng = np.random.default_rng([int(seed), 9])
    drawn = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in PROFILE_RANGES.items()}
    return SensorProfile(f"{name}-random", **drawn)

# D455 colour stream at 640x480; 1280x720 is the same sensor at twice the scale with 120 rows
# of the 4:3 frame cropped away, so fx, fy, cx double and cy = 2 * 238.97 - 120.
_D455_640 = (379.05, 378.68, 321.89, 238.97)


def parse_resolution(text: str) -> tuple[int, int]:
    if text not in RESOLUTIONS:
        raise InputError(f"resolution '{text}' is not supported; use one of: {', '.join(RESOLUTIONS)}")
    w, h = text.split("x")
    return int(w), int(h)


def d455_intrinsics(resolution: str = "640x480") -> CameraIntrinsics:
    """Intrinsics of the D455 colour stream (undistorted: plumb_bob, D = 0)."""
    width, height = parse_resolution(resolution)
    fx, fy, cx, cy = _D455_640
    if width == 1280:
        fx, fy, cx, cy = 2 * fx, 2 * fy, 2 * cx, 2 * cy - 120.0
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return CameraIntrinsics(K=K, width=width, height=height, D=np.zeros(5), distortion_model="plumb_bob")


# Depth as the depth imager records it (realsense-ros without align_depth.enable, the
# RealSense Viewer): its own 848x480 stream with a wider view than colour's, and the colour
# camera 15 mm along x with a small tilt, as a D4xx's factory extrinsics are (realsense-ros
# reports depth_to_color translations of about 15 mm and rotations of a few tenths of a degree).
UNALIGNED_DEPTH_SIZE = (848, 480)
UNALIGNED_DEPTH_K = ((426.0, 0.0, 424.2), (0.0, 426.0, 239.6), (0.0, 0.0, 1.0))
DEPTH_TO_COLOUR_TRANSLATION_M = (0.0150, 0.0002, 0.0004)
DEPTH_TO_COLOUR_ROTATION_DEG = (0.12, -0.25, 0.05)      # about x, y, z


@dataclass(frozen=True)
class UnalignedDepth:
    """A depth imager beside the colour camera: its intrinsics and where colour sits."""
    intrinsics: CameraIntrinsics
    colour_from_depth: np.ndarray       # (4, 4) depth optical frame -> colour optical frame


def unaligned_depth_sensor() -> UnalignedDepth:
    """The D4xx-like depth imager of ``UNALIGNED_DEPTH_*`` / ``DEPTH_TO_COLOUR_*``."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", DEPTH_TO_COLOUR_ROTATION_DEG, degrees=True).as_matrix()
    T[:3, 3] = DEPTH_TO_COLOUR_TRANSLATION_M
    w, h = UNALIGNED_DEPTH_SIZE
    return UnalignedDepth(CameraIntrinsics(K=np.array(UNALIGNED_DEPTH_K), width=w, height=h, D=np.zeros(5),
                                           distortion_model="plumb_bob"), T)


@functools.lru_cache(maxsize=4)
def _vignetting(width: int, height: int) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    r2 = ((x - width / 2) ** 2 + (y - height / 2) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
    v = (1.0 - 0.22 * r2).astype(np.float32)
    return np.ascontiguousarray(np.repeat(v[:, :, None], 3, axis=2))


def _randn_like(shape, seed: int) -> np.ndarray:
    """Standard normal float32 noise; OpenCV's generator is ~3x faster than numpy's."""
    out = np.empty(shape, np.float32)
    flat = out.reshape(shape[0], -1)
    cv2.setRNGSeed(int(seed) & 0x7FFFFFFF)
    cv2.randn(flat, 0.0, 1.0)
    return out


def simulate_colour(radiance: np.ndarray, seed: int, exposure: float = 1.0) -> np.ndarray:
    """rgb8 from noise-free radiance (H, W, 3) float32 in ~[0, 1]."""
    h, w = radiance.shape[:2]
    img = cv2.GaussianBlur(radiance, (3, 3), 0.6)
    img *= _vignetting(w, h) * np.float32(exposure)
    # Shot noise grows with the signal; read noise is a floor (units of full scale).
    sigma = np.sqrt(np.maximum(img, 0) * np.float32(2.5e-4) + np.float32(2.0e-5))
    img += sigma * _randn_like(img.shape, seed)
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def correlated_randn(shape, seed: int, correlation_px: float) -> np.ndarray:
    """Standard normal noise smooth over ``correlation_px`` pixels: white noise blurred by a
    Gaussian of that sigma, scaled back to unit variance (the blur divides the variance of
    white noise by the sum of its squared weights)."""
    white = _randn_like(shape, seed)
    k = cv2.getGaussianKernel(2 * int(np.ceil(3 * correlation_px)) + 1, correlation_px).ravel()
    smooth = cv2.sepFilter2D(white, -1, k, k, borderType=cv2.BORDER_REFLECT)
    return smooth / np.float32(np.sum(k * k))


def simulate_depth(depth_m: np.ndarray, fx: float, seed: int, correlation_px: float = 0.0,
                   profile: SensorProfile | None = None) -> np.ndarray:
    """16UC1 millimetres (0 = invalid) from true depth (H, W) float32 metres, inf = nothing.
    ``correlation_px`` > 0: the noise is smooth over about that many pixels (see the module
    docstring), 0: independent per pixel. ``profile``: how the sensor behaves (default "d455";
    see ``SensorProfile``); what a profile adds comes from random streams of its own."""
    profile = SENSOR_PROFILES["d455"] if profile is None else profile
    h, w = depth_m.shape
    finite = np.isfinite(depth_m)
    z = np.where(finite, depth_m, np.float32(50.0)).astype(np.float32)
    rng = np.random.default_rng(seed)
    invalid = ~finite | (z < MIN_RANGE_M) | (z > MAX_RANGE_M)
    # Depth discontinuities: stereo matching fails where the 3x3 window spans two surfaces.
    kernel = np.ones((3, 3), np.uint8)
    near, far = cv2.erode(z, kernel), cv2.dilate(z, kernel)
    edge = far - near > np.float32(EDGE_SPREAD_REL) * z + np.float32(0.004)
    # Occlusion shadow: depth is matched from the left imager; background pixels just left of
    # a nearer surface are hidden from the right imager (disparity in colour pixels).
    # Pixel u is hidden when some pixel j > u has disp[j] - (j - u) > disp[u], i.e. when the
    # running maximum of (disp - column) to its right exceeds its own: one pass per row.
    disp = np.float32(fx * STEREO_BASELINE_M) / z
    a = disp - np.arange(w, dtype=np.float32)[None, :]
    right_max = np.full((h, w), -np.inf, np.float32)
    right_max[:, :-1] = np.maximum.accumulate(a[:, :0:-1], axis=1)[:, ::-1]
    shadow = right_max > a + np.float32(0.5)
    invalid |= shadow
    # Dropouts in small blobs (low-texture IR patches, speckle): smooth random field, threshold.
    field = rng.random((h // 8 + 2, w // 8 + 2), dtype=np.float32)
    field = cv2.resize(field, (w + 16, h + 16), interpolation=cv2.INTER_CUBIC)[8:8 + h, 8:8 + w]
    invalid |= field > np.float32(DROPOUT_THRESHOLD)
    if profile.edge_dropout >= 1.0:
        invalid |= edge
    else:
        # Some edge pixels have no depth, some of the rest mix the two surfaces (the matcher's
        # window straddles the edge: a depth anywhere between them), the rest keep their own.
        edge_rng = np.random.default_rng([seed, 1])
        pick = edge_rng.random((h, w), dtype=np.float32)
        dropped = edge & (pick < np.float32(profile.edge_dropout))
        flying = edge & ~dropped & (pick < np.float32(profile.edge_dropout + (1.0 - profile.edge_dropout) * profile.flying))
        far_seen = np.where(far < np.float32(MAX_RANGE_M), far, near)        # not towards "nothing"
        z = np.where(flying, near + edge_rng.random((h, w), dtype=np.float32) * (far_seen - near), z)
        invalid |= dropped
    if profile.speckle > 0:         # isolated single-pixel dropouts anywhere
        invalid |= np.random.default_rng([seed, 2]).random((h, w), dtype=np.float32) < np.float32(profile.speckle)
    unit = (correlated_randn((h, w), seed + 7919, correlation_px) if correlation_px > 0
            else _randn_like((h, w), seed + 7919))
    noisy = z + (np.float32(profile.noise_per_m) * z * z + np.float32(profile.noise_floor_m)) * unit
    if profile.disparity_step_px > 0:
        # The camera measures disparity in steps; depth is focal length x baseline / disparity.
        fb = np.float32(DEPTH_IMAGER_FX_PX * STEREO_BASELINE_M)
        step = np.float32(profile.disparity_step_px)
        noisy = fb / (np.maximum(np.rint(fb / np.maximum(noisy, np.float32(1e-3)) / step), 1) * step)
    mm = np.rint(noisy * 1000.0)
    mm[invalid | (mm <= 0)] = 0
    return np.clip(mm, 0, 65535).astype(np.uint16)
