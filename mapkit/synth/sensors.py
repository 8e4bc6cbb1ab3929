"""Sensor models: extrinsics, pinhole intrinsics, the GPS error process, and IMU synthesis.

Frames (REP-103/105): ``base_link`` is x forward, y left, z up, on the road surface under the
centre of the rear axle. A camera's mount is given for its body (x forward, y left, z up); the
published ``camera_front`` frame is the optical frame (x right, y down, z forward), so
``base_from_camera = base_from_camera_body @ BODY_FROM_OPTICAL``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from mapkit.core.geometry import make_pose
from mapkit.synth.config import CameraConfig, GpsConfig, ImuConfig, MountConfig, SynthConfig

BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
GRAVITY_M_S2 = 9.80665

FRAME_BASE = "base_link"
FRAME_CAMERA = "camera_front"
FRAME_LIDAR = "lidar"
FRAME_GPS = "gps"
FRAME_IMU = "imu"
FRAME_WORLD = "world"


def mount_pose(m: MountConfig) -> np.ndarray:
    """``base_from_sensor_body`` of a mount (roll, pitch, yaw applied as extrinsic x, y, z)."""
    R = Rotation.from_euler("xyz", np.radians(m.rpy_deg)).as_matrix()
    return make_pose(R, np.asarray(m.xyz_m, float))


def extrinsics(cfg: SynthConfig) -> dict[str, np.ndarray]:
    """``base_from_<frame>`` of every sensor frame (the camera's is its optical frame)."""
    cam = mount_pose(cfg.camera.mount)
    cam[:3, :3] = cam[:3, :3] @ BODY_FROM_OPTICAL
    out = {FRAME_CAMERA: cam, FRAME_GPS: mount_pose(cfg.gps.mount)}
    if cfg.lidar.enabled:
        out[FRAME_LIDAR] = mount_pose(cfg.lidar.mount)
    if cfg.imu.enabled:
        out[FRAME_IMU] = mount_pose(cfg.imu.mount)
    return out


def intrinsics(cam: CameraConfig) -> np.ndarray:
    """3x3 K of an ideal pinhole: square pixels, principal point at the image centre.

    Pixel (u, v) has its centre at integer coordinates (OpenCV convention), so cx = (W - 1) / 2.
    """
    fx = (cam.width / 2.0) / np.tan(np.radians(cam.hfov_deg) / 2.0)
    return np.array([[fx, 0.0, (cam.width - 1) / 2.0], [0.0, fx, (cam.height - 1) / 2.0], [0.0, 0.0, 1.0]])


def pixel_rays_camera(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Unit ray directions (H*W, 3) in the optical frame, row-major over pixels."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# --- GPS --------------------------------------------------------------------------------------------


@dataclass
class GpsErrorSeries:
    """A simulated error series at the receiver rate, ENU metres, by component."""

    dt_s: float
    white_enu: np.ndarray  # (n, 3)
    bias_enu: np.ndarray  # (n, 3) first-order Gauss-Markov
    multipath_enu: np.ndarray  # (n, 3) piecewise-constant jumps
    valid: np.ndarray  # (n,) False during dropouts
    n_multipath_events: int
    n_dropout_events: int

    @property
    def total_enu(self) -> np.ndarray:
        return self.white_enu + self.bias_enu + self.multipath_enu


class GpsErrorModel:
    """White noise + Gauss-Markov bias + multipath jumps + dropouts (Poisson events).

    Horizontal components have standard deviations ``white_sigma_m`` and ``bias_sigma_m``; the
    vertical ones are ``vertical_factor`` times larger. A multipath event adds a constant offset
    (2-D normal, ``multipath_sigma_m`` per axis) for an exponentially distributed duration; a dropout
    removes fixes for one. Events arrive as Poisson processes and may overlap, so the expected
    fraction of time in a dropout is ``1 - exp(-rate * mean duration)``.
    """

    def __init__(self, cfg: GpsConfig):
        self.cfg = cfg

    @property
    def dt_s(self) -> float:
        return 1.0 / self.cfg.rate_hz

    @property
    def covariance_enu_m2(self) -> np.ndarray:
        """What the receiver reports: white plus bias variance (it does not know about multipath)."""
        c = self.cfg
        h = c.white_sigma_m**2 + c.bias_sigma_m**2
        return np.diag([h, h, h * c.vertical_factor**2])

    @property
    def expected_dropout_fraction(self) -> float:
        return float(1.0 - np.exp(-self.cfg.dropout_rate_hz * self.cfg.dropout_duration_s))

    def _events(self, n: int, rate_hz: float, mean_s: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        T = n * self.dt_s
        k = int(rng.poisson(rate_hz * T)) if rate_hz > 0 else 0
        start = np.sort(rng.uniform(0, T, k))
        dur = rng.exponential(mean_s, k)
        i0 = np.clip(np.ceil(start / self.dt_s).astype(int), 0, n)
        i1 = np.clip(np.ceil((start + dur) / self.dt_s).astype(int), 0, n)
        return i0, i1

    def simulate(self, n: int, rng: np.random.Generator) -> GpsErrorSeries:
        c = self.cfg
        scale = np.array([1.0, 1.0, c.vertical_factor])
        white = rng.standard_normal((n, 3)) * c.white_sigma_m * scale
        phi = float(np.exp(-self.dt_s / c.bias_tau_s))
        eps = rng.standard_normal((n, 3)) * np.sqrt(1.0 - phi * phi)
        b0 = rng.standard_normal(3)  # stationary start
        from scipy.signal import lfilter  # here: scipy.signal takes half a second to import, in every worker

        bias = lfilter([1.0], [1.0, -phi], eps, axis=0, zi=(phi * b0)[None, :])[0] * c.bias_sigma_m * scale
        i0, i1 = self._events(n, c.multipath_rate_hz, c.multipath_duration_s, rng)
        offs = rng.standard_normal((len(i0), 2)) * c.multipath_sigma_m
        multipath = np.zeros((n, 3))
        for a, b, off in zip(i0, i1, offs, strict=True):  # a few events a session: exact zeros outside them
            multipath[a:b, :2] += off
        d0, d1 = self._events(n, c.dropout_rate_hz, c.dropout_duration_s, rng)
        cover = np.zeros(n + 1, int)
        np.add.at(cover, d0, 1)
        np.add.at(cover, d1, -1)
        valid = np.cumsum(cover)[:n] == 0
        return GpsErrorSeries(self.dt_s, white, bias, multipath, valid, len(i0), len(d0))


# --- IMU --------------------------------------------------------------------------------------------


def imu_from_poses(stamps_ns: np.ndarray, world_from_imu: np.ndarray, cfg: ImuConfig, rng: np.random.Generator):
    """Angular velocity and specific force in the IMU frame from evenly spaced poses.

    Central differences of the ground truth (second order in dt), plus a constant bias per session
    and white noise. Returns (gyro (n, 3) rad/s, accel (n, 3) m/s^2).
    """
    t = (np.asarray(stamps_ns, np.int64) - stamps_ns[0]) * 1e-9
    p = world_from_imu[:, :3, 3]
    R = world_from_imu[:, :3, :3]
    n = len(t)
    acc_w = np.zeros((n, 3))
    gyro = np.zeros((n, 3))
    if n >= 3:
        dt_prev = t[1:-1] - t[:-2]
        dt_next = t[2:] - t[1:-1]
        v_prev = (p[1:-1] - p[:-2]) / dt_prev[:, None]
        v_next = (p[2:] - p[1:-1]) / dt_next[:, None]
        acc_w[1:-1] = (v_next - v_prev) / ((dt_prev + dt_next) / 2)[:, None]
        acc_w[0], acc_w[-1] = acc_w[1], acc_w[-2]
        rel = Rotation.from_matrix(np.swapaxes(R[:-2], 1, 2) @ R[2:]).as_rotvec()
        gyro[1:-1] = rel / (dt_prev + dt_next)[:, None]
        gyro[0], gyro[-1] = gyro[1], gyro[-2]
    f_body = np.einsum("nji,nj->ni", R, acc_w + np.array([0.0, 0.0, GRAVITY_M_S2]))
    gyro = gyro + rng.normal(0, cfg.gyro_bias_rad_s, 3) + rng.standard_normal((n, 3)) * cfg.gyro_noise_rad_s
    f_body = f_body + rng.normal(0, cfg.accel_bias_m_s2, 3) + rng.standard_normal((n, 3)) * cfg.accel_noise_m_s2
    return gyro, f_body
