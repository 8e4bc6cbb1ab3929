"""CPU rendering with open3d's RaycastingScene: a shaded pinhole camera and a spinning LiDAR.

A camera frame is one ``cast_rays`` call for all pixels plus one ``test_occlusions`` call toward
the sun for the lit ones (cast shadows); everything else is vectorised numpy on the hits:
per-triangle attributes gathered by primitive id, procedural textures (``appearance``), sun, sky,
street lamps and headlights, fog, rain and snow, then the camera's exposure, white balance,
vignetting, noise and tone curve. The renderer also returns the range and z-depth of every pixel
(``inf`` where a pixel sees the sky), so that tests can check pixels against the mesh.

A LiDAR sweep is one ``cast_rays`` call with each azimuth column fired from the sensor pose at its
own firing time: the points are what the sensor measures (range along the beam in its frame at
that instant), so a consumer sees motion distortion unless it undistorts with ``time``.

Moving cars (:mod:`mapkit.synth.traffic`) are a second scene built for each frame's time; each ray
takes the nearer of its hits in the two, and each scene's hits are shaded from its own triangle table.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from mapkit.synth.appearance import F32, Conditions, Hits, TriangleTable, dot3, f32, sky_radiance, surface, to_srgb8
from mapkit.synth.config import CameraConfig, LidarConfig
from mapkit.synth.sensors import intrinsics, pixel_rays_camera
from mapkit.synth.traffic import Traffic
from mapkit.synth.world import Geometry, Mat, Town

SHADOW_BIAS_M = 0.02
LAMP_INTENSITY = 40.0
HEADLIGHT_INTENSITY = 2000.0
LAMPS_PER_FRAME = 8
LAMP_REACH_M = 40.0
LIDAR_BEAM_DIVERGENCE_RAD = 0.003


def available_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@dataclass
class CameraRender:
    rgb: np.ndarray  # (H, W, 3) uint8 sRGB
    range_m: np.ndarray  # (H, W) float32 distance along each pixel's ray, inf for sky
    depth_m: np.ndarray  # (H, W) float32 z-depth in the optical frame, inf for sky
    material: np.ndarray  # (H, W) uint8 (world.Mat; 0 for sky)


@dataclass
class LidarSweep:
    points_xyz: np.ndarray  # (N, 3) float32 in the sensor frame at each point's firing time
    intensity: np.ndarray  # (N,) float32 0..255
    time_s: np.ndarray  # (N,) float32 seconds after the sweep's stamp
    ring: np.ndarray  # (N,) uint16, 0 = lowest beam
    range_m: np.ndarray  # (N,) float32 measured range (with noise)
    moving: np.ndarray  # (N,) bool: the return hit a moving car


@dataclass
class _Layer:
    """A scene and the per-triangle attributes its hits are shaded with."""

    scene: Any  # open3d RaycastingScene
    material: np.ndarray  # (T,) uint8
    table: TriangleTable
    tri_offset: np.ndarray  # first triangle of each geometry added to the scene

    @staticmethod
    def of(parts: list[Geometry]) -> _Layer:
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        tri_offset = np.zeros(len(parts), np.int64)
        off = 0
        for k, g in enumerate(parts):
            # open3d's generated stub makes Tensor's dtype and device required; they default to the array's and the CPU
            scene.add_triangles(
                o3d.core.Tensor(g.vertices.astype(np.float32)),  # type: ignore[call-overload]
                o3d.core.Tensor(g.triangles.astype(np.uint32)),  # type: ignore[call-overload]
            )
            tri_offset[k] = off
            off += g.n_triangles
        cat = Geometry.concat(parts) if len(parts) > 1 else parts[0]
        # origin, axis_u, axis_v, aux packed per triangle: one gather per material slice
        table = TriangleTable(
            np.ascontiguousarray(np.concatenate([cat.origin, cat.axis_u, cat.axis_v, cat.aux], axis=1), F32),
            cat.style.astype(np.int64),
            cat.object_id,
        )
        return _Layer(scene, cat.material, table, tri_offset)


class Renderer:
    """A scene (static town plus one session's parked cars, and its moving cars placed at each frame's time)
    and the sensors that look at it."""

    def __init__(
        self,
        town: Town,
        parked: Geometry | None,
        camera: CameraConfig,
        lidar: LidarConfig,
        nthreads: int | None = None,
        traffic: Traffic | None = None,
    ):
        import open3d as o3d

        self._o3d = o3d
        self.town = town
        self.styles = town.styles
        self.traffic = traffic
        self.static = _Layer.of([town.geometry] + ([parked] if parked is not None and parked.n_triangles else []))
        self.scene = self.static.scene
        # open3d's default (0) oversubscribes a small machine; one thread per available core is faster
        self.nthreads = nthreads or available_cores()
        # camera
        self.camera = camera
        self.K = intrinsics(camera)
        self.W, self.H = camera.width, camera.height
        self.rays_cam = pixel_rays_camera(self.K, self.W, self.H).astype(F32)
        r2 = ((np.arange(self.W) - self.K[0, 2]) ** 2)[None, :] + ((np.arange(self.H) - self.K[1, 2]) ** 2)[:, None]
        self.vignette = (1.0 - 0.3 * r2 / r2.max()).astype(F32).reshape(-1, 1)
        # standard normal samples for sensor noise; each frame reads them at a random offset
        n_px = self.W * self.H * 3
        self._noise_bank = np.random.default_rng(20240).standard_normal(2 * n_px, dtype=F32)
        # lidar: beams (elevations) x azimuth columns, columns fired in time order
        self.lidar = lidar
        el = np.radians(np.linspace(lidar.vertical_fov_deg[0], lidar.vertical_fov_deg[1], lidar.beams))
        az = np.pi - 2 * np.pi * np.arange(lidar.azimuth_steps) / lidar.azimuth_steps  # clockwise from behind
        ce, se = np.cos(el)[None, :], np.sin(el)[None, :]
        self.lidar_dirs = np.stack(
            [ce * np.cos(az)[:, None], ce * np.sin(az)[:, None], np.broadcast_to(se, (len(az), len(el)))], -1
        ).astype(F32)  # (A, B, 3)
        self.lidar_col_time_s = np.arange(lidar.azimuth_steps) / lidar.azimuth_steps / lidar.rate_hz

    # --- ray casting ----------------------------------------------------------------------------
    def cast(self, origins: np.ndarray, dirs: np.ndarray, layer: _Layer | None = None) -> dict:
        rays = np.empty((len(dirs), 6), F32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs
        scene = (layer or self.static).scene
        # open3d's generated stub makes Tensor's dtype and device required; they default to the array's and the CPU
        out = scene.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.nthreads)  # type: ignore[call-overload]
        return {k: out[k].numpy() for k in ("t_hit", "geometry_ids", "primitive_ids", "primitive_normals")}

    def _moving(self, t_ns: int | None) -> _Layer | None:
        """The moving cars' scene at ``t_ns`` (None without traffic, or with none on the road)."""
        if self.traffic is None or t_ns is None:
            return None
        g = self.traffic.geometry_at(t_ns)
        return None if g is None else _Layer.of([g])

    def cast_all(
        self, origins: np.ndarray, dirs: np.ndarray, t_ns: int | None
    ) -> list[tuple[_Layer, dict, np.ndarray]]:
        """Per scene (the static one, then the moving cars' at ``t_ns`` if any): the layer, its cast, and which
        rays it is the nearest hit of."""
        out = self.cast(origins, dirs)
        moving = self._moving(t_ns)
        if moving is None:
            return [(self.static, out, np.isfinite(out["t_hit"]))]
        out_m = self.cast(origins, dirs, moving)
        nearer = out_m["t_hit"] < out["t_hit"]  # inf where either misses
        return [(self.static, out, np.isfinite(out["t_hit"]) & ~nearer), (moving, out_m, nearer)]

    def _sorted_hits(self, out: dict, mask: np.ndarray, layer: _Layer | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the rays that hit and their triangle ids, ordered by material."""
        layer = layer or self.static
        idx = np.flatnonzero(mask)
        gid = out["geometry_ids"][idx]
        tri = out["primitive_ids"][idx].astype(np.int64)
        if len(layer.tri_offset) > 1:
            tri += layer.tri_offset[np.minimum(gid, len(layer.tri_offset) - 1)]
        order = np.argsort(layer.material[tri], kind="stable")
        return idx[order], tri[order]

    def _hits(
        self,
        origin_rows: np.ndarray,
        dirs: np.ndarray,
        out: dict,
        idx: np.ndarray,
        tri: np.ndarray,
        footprint_per_m: float,
        layer: _Layer | None = None,
    ) -> Hits:
        layer = layer or self.static
        t = out["t_hit"][idx]
        d = dirs[idx]
        p = origin_rows + d * t[:, None]
        nrm = out["primitive_normals"][idx]
        facing = dot3(nrm, d)
        nrm *= np.where(facing > 0, F32(-1), F32(1))[:, None]
        cos_i = np.maximum(np.abs(facing), F32(0.2))
        return Hits(p, nrm, d, t, t * (F32(footprint_per_m) / cos_i), layer.material[tri], tri, layer.table)

    # --- camera ---------------------------------------------------------------------------------
    def render_camera(
        self,
        world_from_camera: np.ndarray,
        cond: Conditions,
        rng: np.random.Generator,
        world_from_base: np.ndarray | None = None,
        t_ns: int | None = None,
    ) -> CameraRender:
        """One frame from ``world_from_camera``; ``t_ns`` places the moving cars (none without it)."""
        R = world_from_camera[:3, :3].astype(F32)
        o = world_from_camera[:3, 3]
        d = self.rays_cam @ R.T
        radiance = np.zeros((len(d), 3), F32)
        mat = np.zeros(len(d), np.uint8)
        t_hit = np.full(len(d), np.inf, F32)
        hit = np.zeros(len(d), bool)
        for layer, out, mine in self.cast_all(np.broadcast_to(o.astype(F32), d.shape), d, t_ns):
            idx, tri = self._sorted_hits(out, mine, layer)
            h = self._hits(o.astype(F32)[None], d, out, idx, tri, 1.0 / self.K[0, 0], layer)
            surf = surface(h, self.styles, cond)
            radiance[idx] = self._shade(h, surf, cond, world_from_base)
            mat[idx] = h.mat
            t_hit[idx] = out["t_hit"][idx]
            hit[idx] = True
        sky_idx = np.nonzero(~hit)[0]
        if len(sky_idx):
            radiance[sky_idx] = sky_radiance(d[sky_idx], cond)
        # fog / aerial perspective (extinction 3 / visibility), exposure, white balance, vignetting
        rng_m = np.where(hit, t_hit, F32(1500.0))
        T = np.exp(rng_m * F32(-3.0 / cond.fog_visibility_m))[:, None]
        g = self.vignette * F32(cond.exposure_gain)
        Tg = T * g
        linear = radiance
        linear *= Tg
        linear *= cond.white_balance[None]
        linear += (g - Tg) * (cond.fog_rgb * cond.white_balance)[None]
        linear = self._weather_overlay(linear, cond, rng)
        # sensor noise (shot + read), stronger at high gain
        g_rel = F32(max(cond.exposure_gain, 1.0) ** 0.5)
        sigma = np.maximum(linear, F32(0))
        sigma *= F32(cond.shot_noise * g_rel)
        sigma += F32(cond.read_noise * g_rel) ** 2
        np.sqrt(sigma, out=sigma)
        start = int(rng.integers(0, len(self._noise_bank) - linear.size))
        sigma *= self._noise_bank[start : start + linear.size].reshape(linear.shape)
        linear += sigma
        img = to_srgb8(linear).reshape(self.H, self.W, 3)
        if cond.rain > 0 or cond.weather == "foggy":
            img = cv2.GaussianBlur(img, (0, 0), 0.8)
        range_m = t_hit.reshape(self.H, self.W)  # inf where a ray hits nothing
        return CameraRender(
            img, range_m, range_m * self.rays_cam[:, 2].reshape(self.H, self.W), mat.reshape(self.H, self.W)
        )

    def _shadow_rays(self, p: np.ndarray, n: np.ndarray, sun: np.ndarray) -> np.ndarray:
        rays = np.empty((len(p), 6), F32)
        rays[:, :3] = p + n * SHADOW_BIAS_M
        rays[:, 3:] = sun[None]
        # open3d's generated stub makes Tensor's dtype and device required; they default to the array's and the CPU
        return self.scene.test_occlusions(self._o3d.core.Tensor(rays), nthreads=self.nthreads).numpy()  # type: ignore[call-overload]

    def _sun_visibility(self, h: Hits, lit: np.ndarray, sun: np.ndarray) -> np.ndarray:
        """1 where the sun is not occluded (one shadow ray per lit hit), else 0."""
        vis = np.zeros(len(h.p), F32)
        li = np.flatnonzero(lit)
        if len(li):
            vis[li] = ~self._shadow_rays(h.p[li], h.n[li], sun)
        return vis

    def _shade(self, h: Hits, s, c: Conditions, world_from_base: np.ndarray | None) -> np.ndarray:
        n = h.n
        # sky light on the upper hemisphere plus light bounced off the ground, linear in n_z
        bounce = (c.ambient_rgb * 0.5 + c.sun_rgb * 0.15) * 0.35
        E = (0.55 * c.ambient_rgb + 0.5 * bounce)[None] + n[:, 2:3] * (0.45 * c.ambient_rgb - 0.5 * bounce)[None]
        if c.sun_rgb.max() > 0.01:
            cosi = n @ c.sun_dir_enu
            vis = np.where(cosi > 0, cosi, F32(0)) * self._sun_visibility(h, cosi > 0, c.sun_dir_enu)
            E = E + vis[:, None] * c.sun_rgb[None]
        if c.night > 0.01:
            E = E + c.night * self._lamps(h, c)
            if world_from_base is not None:
                E = E + c.night * self._headlights(h, world_from_base)
        L = s.albedo * E
        if c.night > 0.01:
            L += s.emissive_night * F32(c.night)
        m = np.nonzero(s.mirror > 0.01)[0]
        if len(m):
            d, nn = h.d[m], n[m]
            r = d - 2 * dot3(d, nn)[:, None] * nn
            refl = sky_radiance(r, c)
            if c.night > 0.01:
                refl = refl + c.night * self._lamp_glints(h.p[m], r, c)
            L[m] = L[m] + s.mirror[m, None] * refl
        return L

    def _near_lamps(self, p: np.ndarray) -> np.ndarray:
        lamps = self.town.lamps_xyz
        if not len(lamps):
            return lamps
        centre = p[:: max(1, len(p) // 512)].mean(axis=0)
        dist = np.linalg.norm(lamps[:, :2] - centre[:2], axis=1)
        k = min(LAMPS_PER_FRAME, len(lamps))
        near = np.argpartition(dist, k - 1)[:k]
        return lamps[near].astype(F32)

    def _lamps(self, h: Hits, c: Conditions) -> np.ndarray:
        """Street-lamp irradiance: inverse square, cosine at the surface, brighter below the lamp.
        Lamps share one colour, so a scalar is accumulated on contiguous columns; a lamp's far
        side (beyond LAMP_REACH_M its light is below 1% of a lit patch) is skipped when that saves work."""
        cols = [np.ascontiguousarray(h.p[:, k]) for k in range(3)] + [np.ascontiguousarray(h.n[:, k]) for k in range(3)]
        acc = np.zeros(len(h.p), F32)
        for lamp in self._near_lamps(h.p):
            dx = lamp[0] - cols[0]
            dy = lamp[1] - cols[1]
            r2 = dx * dx + dy * dy
            near = None
            if (r2 < LAMP_REACH_M**2).mean() < 0.5:
                near = np.flatnonzero(r2 < F32(LAMP_REACH_M**2))
                dx, dy, r2 = dx[near], dy[near], r2[near]
            px, py, pz, nx, ny, nz = cols if near is None else [x[near] for x in cols]
            dz = lamp[2] - pz
            d2 = r2 + dz * dz
            inv = 1.0 / np.sqrt(d2)
            cosl = np.maximum((dx * nx + dy * ny + dz * nz) * inv, F32(0))
            w = LAMP_INTENSITY * cosl * (0.25 + 0.75 * np.clip(-dz * inv, 0, 1)) / (d2 + 1.0)  # lamps shine downward
            if near is None:
                acc += w
            else:
                acc[near] += w
        return acc[:, None] * c.lamp_rgb[None]

    def _lamp_glints(self, p: np.ndarray, r: np.ndarray, c: Conditions) -> np.ndarray:
        """Mirror images of lamps in glass and wet surfaces (a sharp lobe around the reflection)."""
        G = np.zeros((len(p), 3), F32)
        for lamp in self._near_lamps(p):
            v = lamp[None] - p
            dist = np.sqrt(dot3(v, v))
            cosr = dot3(v, r) / dist
            k = np.flatnonzero(cosr > 0.985)  # 0.985**400 < 0.3%
            if len(k):
                G[k] += (40.0 * np.exp(400.0 * np.log(cosr[k])) / (1.0 + 0.01 * dist[k]))[:, None] * c.lamp_rgb[None]
        return G

    def _headlights(self, h: Hits, world_from_base: np.ndarray) -> np.ndarray:
        """Two low beams: aimed about 1.5 deg down (brightest on the road 15-30 m ahead, dim close
        to the car), +-25 deg wide, nothing above the lamps' horizon; inverse square."""
        fwd = world_from_base[:3, 0].astype(F32)
        left = world_from_base[:3, 1].astype(F32)
        up = world_from_base[:3, 2].astype(F32)
        px, py, pz = (np.ascontiguousarray(h.p[:, k]) for k in range(3))
        nx, ny, nz = (np.ascontiguousarray(h.n[:, k]) for k in range(3))
        acc = np.zeros(len(px), F32)
        for side in (-0.75, 0.75):
            pos = (world_from_base @ np.array([3.7, side, 0.7, 1.0]))[:3].astype(F32)
            vx, vy, vz = px - pos[0], py - pos[1], pz - pos[2]
            d2 = vx * vx + vy * vy + vz * vz
            inv = 1.0 / np.sqrt(d2)
            f = (vx * fwd[0] + vy * fwd[1] + vz * fwd[2]) * inv
            lat = (vx * left[0] + vy * left[1] + vz * left[2]) * inv
            down = -(vx * up[0] + vy * up[1] + vz * up[2]) * inv
            beam = np.exp(
                -(((down - F32(0.026)) * F32(1 / 0.045)) ** 2) - (lat / np.maximum(f, F32(0.05)) * F32(1 / 0.45)) ** 2
            )
            beam *= (f > 0) & (down > -0.01)
            cosl = np.maximum(-(vx * nx + vy * ny + vz * nz) * inv, F32(0))
            acc += HEADLIGHT_INTENSITY * beam * cosl / (d2 + 1.0)
        return acc[:, None] * f32(1.0, 0.95, 0.85)[None]

    def _weather_overlay(self, linear: np.ndarray, c: Conditions, rng: np.random.Generator) -> np.ndarray:
        """Rain streaks and falling snow in image space (random per frame, from the frame's rng)."""
        if c.rain <= 0 and c.snowfall <= 0:
            return linear
        H, W = self.H, self.W
        scale = W / 640.0
        level = F32(0.28 * (1 - 0.7 * c.night))
        layer = np.zeros((H, W), np.float32)
        if c.rain > 0:
            n = int(700 * c.rain * scale * scale)
            x0 = rng.uniform(0, W, n)
            y0 = rng.uniform(-0.2 * H, H, n)
            length = rng.uniform(12, 40, n) * scale
            ang = np.radians(rng.normal(100, 4, n))
            pts = np.stack(
                [np.stack([x0, y0], 1), np.stack([x0 + length * np.cos(ang), y0 + length * np.sin(ang)], 1)], 1
            )
            cv2.polylines(layer, list(np.round(pts * 16).astype(np.int32)), False, 1.0, 1, cv2.LINE_AA, 4)
            layer *= 0.6
        if c.snowfall > 0:
            for size, count in ((1.6, 500), (0.8, 1400)):
                k = int(count * c.snowfall * scale * scale)
                flakes = np.zeros((H, W), np.float32)
                flakes[rng.integers(0, H, k), rng.integers(0, W, k)] = rng.uniform(4.0, 9.0, k).astype(np.float32)
                layer += cv2.GaussianBlur(flakes, (0, 0), size * scale)
        return linear + (np.clip(layer, 0, 2.0) * level).reshape(-1, 1)

    # --- lidar ----------------------------------------------------------------------------------
    def scan_lidar(
        self, world_from_lidar_cols: np.ndarray, rng: np.random.Generator, t_ns: int | None = None
    ) -> LidarSweep:
        """One sweep; ``world_from_lidar_cols`` (A, 4, 4) is the sensor pose at each column's firing time;
        ``t_ns`` (the sweep's middle) places the moving cars (none without it)."""
        A, B = self.lidar_dirs.shape[:2]
        R = world_from_lidar_cols[:, :3, :3]
        dirs_w = np.matmul(self.lidar_dirs, np.swapaxes(R, 1, 2).astype(F32)).reshape(-1, 3)
        origins = np.repeat(world_from_lidar_cols[:, :3, 3], B, axis=0).astype(F32)
        t = np.full(len(dirs_w), np.inf, F32)
        refl = np.zeros(len(dirs_w), F32)
        cos_i = np.zeros(len(dirs_w), F32)
        moving = np.zeros(len(dirs_w), bool)
        for k, (layer, out, mine) in enumerate(self.cast_all(origins, dirs_w, t_ns)):
            tk = out["t_hit"]
            ok = mine & (tk >= self.lidar.min_range_m) & (tk <= self.lidar.max_range_m)
            idx, tri = self._sorted_hits(out, ok, layer)
            h = self._hits(origins[idx], dirs_w, out, idx, tri, LIDAR_BEAM_DIVERGENCE_RAD, layer)
            refl[idx] = surface(h, self.styles, None).reflectivity
            cos_i[idx] = np.abs(dot3(h.d, h.n))
            t[idx] = tk[idx]
            moving[idx] = k > 0
        idx = np.flatnonzero(np.isfinite(t))  # in firing order: column by column, beams within a column
        intensity = np.clip(
            255.0 * refl[idx] * np.sqrt(cos_i[idx]) * (1.0 / (1.0 + (t[idx] / 80.0) ** 2)), 0, 255
        ).astype(F32)
        r = t[idx].astype(np.float64)
        if self.lidar.range_noise_m > 0:
            r = r + rng.standard_normal(len(r)) * self.lidar.range_noise_m
        dirs_l = self.lidar_dirs.reshape(-1, 3)[idx].astype(np.float64)
        pts = (dirs_l * r[:, None]).astype(F32)
        col = idx // B
        return LidarSweep(
            pts,
            intensity,
            self.lidar_col_time_s[col].astype(F32),
            (idx % B).astype(np.uint16),
            r.astype(F32),
            moving[idx],
        )


def ground_truth_mesh_scene(vertices: np.ndarray, triangles: np.ndarray):
    """An open3d RaycastingScene of a mesh (for distance checks against the ground truth)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    # open3d's generated stub makes Tensor's dtype and device required; they default to the array's and the CPU
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(vertices, np.float32)),  # type: ignore[call-overload]
        o3d.core.Tensor(np.asarray(triangles, np.uint32)),  # type: ignore[call-overload]
    )
    return scene


__all__ = ["Renderer", "CameraRender", "LidarSweep", "ground_truth_mesh_scene", "Mat"]
