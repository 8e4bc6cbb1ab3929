"""Registering two clouds: coarse-to-fine point-to-plane ICP, its scoring and the accept/reject decision.

:func:`mapkit.mapping.icp.icp_coarse_to_fine` is the one ICP loop of mapkit: :func:`register_clouds`
feeds it clouds it downsamples itself (submap pairs of ``mapkit align``), and
:func:`mapkit.places.triplets.register_cell` the crops of clouds it downsampled once per session.
:func:`decide` judges a :class:`Registration` under the :class:`IcpConfig` gates and says why in a
:class:`Verdict` (a code to count by, and the text written to pairs.json and qa.md).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from mapkit.core.config import MapkitConfig
from mapkit.mapping.icp import IcpClouds, icp_coarse_to_fine, point_to_plane
from mapkit.multisession.submaps import SessionData, SubmapClouds, submap_points


class IcpConfig(MapkitConfig):
    voxel_sizes_m: list[float] = Field(
        [1.0, 0.5, 0.25, 0.1],
        description="Voxel size of each coarse-to-fine ICP level (m). The fourth level, 0.1 m (the semi-dense "
        "maps' own spacing near the road, below the 0.15 m accuracy goal), was chosen on the tiny town (misalignment "
        "0.118 -> 0.085 m) and scored on the demo (0.091 -> 0.053 m; accepted pairs' true error 0.082 -> 0.043 m): "
        "docs/accuracy.md.",
    )
    max_correspondence_m: list[float] = Field(
        [4.0, 1.5, 0.6, 0.25],
        description="Largest correspondence distance of each level (m); the first bounds the misalignment ICP can pull "
        "in.",
    )
    max_iterations: int = Field(40, ge=1, description="ICP iterations per level.")
    normal_radius_factor: float = Field(
        3.0,
        gt=0,
        description="Normals from neighbours within this many voxels (the semi-dense clouds carry no reliable "
        "normals).",
    )
    normal_max_nn: int = Field(30, ge=5, description="At most this many neighbours per normal.")
    lambda_icp_m: float = Field(
        0.40,
        gt=0,
        description="lambda_ICP: reject a pair whose point-to-plane RMSE after ICP (over correspondences within "
        "eval_distance_m; overall and for the structure alone) exceeds this (semi-dense paper, section 4.1; the paper "
        "gives no value: 0.40 m sits above the demo maps' own noise, whose accepted pairs reach 0.35 m).",
    )
    eval_distance_m: float = Field(
        1.0, gt=0, description="Correspondence distance for the RMSE and fitness that decide acceptance (m)."
    )
    min_fitness: float = Field(
        0.25,
        ge=0,
        le=1,
        description="Reject a pair when fewer than this fraction of source points have a target point within "
        "eval_distance_m.",
    )
    min_structure_fitness: float = Field(
        0.25,
        ge=0,
        le=1,
        description="... and the same for the structure alone (points whose normal is not vertical): the ground fits "
        "any horizontal shift.",
    )
    structure_max_normal_z: float = Field(
        0.7, gt=0, le=1, description="A point is structure when |normal z| is below this."
    )
    max_correction_m: float = Field(
        12.0,
        gt=0,
        description="Reject a pair whose correction moves the pair centre more than this (m): more than GPS can be "
        "off.",
    )
    max_rotation_deg: float = Field(
        5.0, gt=0, description="Reject a pair whose correction rotates more than this (deg)."
    )


# --- registering two clouds ------------------------------------------------------------------------


@dataclass(frozen=True)
class Registration:
    """What ICP made of two clouds: the transform and how well it fits (see :func:`evaluate_alignment`)."""

    target_from_source: np.ndarray  # (4, 4), ENU: maps source points onto the target's
    fitness: float
    rmse_m: float
    structure_fitness: float
    structure_rmse_m: float
    structure_points: int = 0

    @classmethod
    def failed(cls) -> Registration:
        """Too few points to register: no fit (it fails every gate)."""
        return cls(np.eye(4), 0.0, float("nan"), 0.0, float("nan"), 0)


def about_centre(T: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``T`` (acting on coordinates relative to ``centre``, x' = x - c) in ENU coordinates."""
    C = np.eye(4)
    C[:3, 3] = centre
    return C @ T @ np.linalg.inv(C)


def _cloud(points: np.ndarray, origin: np.ndarray):
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64) - origin)
    return pc


def register_clouds(
    source: np.ndarray, target: np.ndarray, centre: np.ndarray, cfg: IcpConfig, structure: bool = True
) -> Registration:
    """Coarse-to-fine point-to-plane ICP of ``source`` onto ``target`` (both ENU, N x 3).

    Works next to ``centre``; each level downsamples both clouds and estimates the target's
    normals. Returns the transform (ENU) with the fitness and point-to-plane RMSE at
    ``cfg.eval_distance_m`` (see :func:`evaluate_alignment`; ``structure=False`` skips the
    structure-only figures).
    """
    import open3d as o3d

    src0, tgt0 = _cloud(source, centre), _cloud(target, centre)

    def level(voxel: float) -> IcpClouds | None:
        src, tgt = src0.voxel_down_sample(voxel), tgt0.voxel_down_sample(voxel)
        if len(src.points) < 10 or len(tgt.points) < 10:
            return None
        tgt.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius_factor * voxel, max_nn=cfg.normal_max_nn)
        )
        return IcpClouds(np.array(src.points), np.array(tgt.points), np.array(tgt.normals))

    T, fine_clouds = icp_coarse_to_fine(level, cfg.voxel_sizes_m, cfg.max_correspondence_m, cfg.max_iterations)
    fine = cfg.voxel_sizes_m[-1]
    if fine_clouds is None:  # stopped early: evaluate at the fine level from scratch
        src, tgt, target_normals = (
            np.asarray(src0.voxel_down_sample(fine).points),
            np.asarray(tgt0.voxel_down_sample(fine).points),
            None,
        )
    else:  # the last level is the fine one: its target normals are already there
        src, tgt, target_normals = fine_clouds.source, fine_clouds.target, fine_clouds.target_normals
    ev = evaluate_alignment(src, tgt, T, fine, cfg, target_normals, structure)
    return Registration(about_centre(T, centre), **ev)


def evaluate_alignment(
    source: np.ndarray,
    target: np.ndarray,
    T: np.ndarray,
    voxel: float,
    cfg: IcpConfig,
    target_normals: np.ndarray | None = None,
    structure: bool = True,
) -> dict:
    """Fitness and point-to-plane RMSE of ``T @ source`` against ``target``, overall and for the
    structure alone.

    Point-to-plane, because two semi-dense maps sample a surface at different points: the
    point-to-point distance measures their sampling, not their alignment. Structure (points whose
    normal is not vertical) is scored on its own because the ground fits any horizontal shift.
    """
    import open3d as o3d

    def normals(pts):
        pc = _cloud(pts, np.zeros(3))
        pc.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.normal_radius_factor * voxel, max_nn=cfg.normal_max_nn)
        )
        return np.asarray(pc.normals)

    rms = lambda v: float(np.sqrt(np.mean(v**2))) if len(v) else float("nan")  # noqa: E731 (a one-line helper local to this function)
    if len(source) == 0 or len(target) == 0:
        return {
            "fitness": 0.0,
            "rmse_m": float("nan"),
            "structure_fitness": 0.0,
            "structure_rmse_m": float("nan"),
            "structure_points": 0,
        }
    moved = source @ T[:3, :3].T + T[:3, 3]
    n_t = normals(target) if target_normals is None else target_normals
    inlier, _, signed = point_to_plane(moved, target, n_t, cfg.eval_distance_m)
    r = np.abs(signed)
    out = {"fitness": float(inlier.mean()), "rmse_m": rms(r)}
    if not structure:
        return {**out, "structure_fitness": out["fitness"], "structure_rmse_m": out["rmse_m"], "structure_points": 0}
    upright = np.abs(normals(source) @ T[:3, :3].T[:, 2]) < cfg.structure_max_normal_z
    r_s = r[upright[inlier]]
    return {
        **out,
        "structure_fitness": float((inlier & upright).sum() / max(1, upright.sum())),
        "structure_rmse_m": rms(r_s),
        "structure_points": int(upright.sum()),
    }


# --- the decision ----------------------------------------------------------------------------------


class Reason(Enum):
    """Why a pair was accepted or rejected (the gate that decided it)."""

    ACCEPTED = "accepted"
    NOT_REGISTERED = "not registered"  # too few points to try (the registration cache's entry)
    FITNESS = "fitness"
    STRUCTURE_FITNESS = "structure fitness"
    RMSE = "RMSE"
    STRUCTURE_RMSE = "structure RMSE"
    CORRECTION = "correction"
    ROTATION = "rotation"
    TOO_FEW_POINTS = "too few points"
    INCONSISTENT = "inconsistent with the other registrations"  # rejected by the pose graph
    RECORDED = "recorded"  # read back from a file: only its text is known

    @property
    def tally(self) -> str:
        """The reason's key in qa.json's ``rejected_by_reason`` (both structure gates count as "structure")."""
        return "structure" if self in (Reason.STRUCTURE_FITNESS, Reason.STRUCTURE_RMSE) else self.value


@dataclass(frozen=True)
class Verdict:
    """A decision on a pair: its :class:`Reason` and the human text (``headline (detail)``) that
    pairs.json and qa.md show."""

    reason: Reason
    headline: str
    detail: str = ""

    @property
    def text(self) -> str:
        return f"{self.headline} ({self.detail})" if self.detail else self.headline

    @property
    def accepted(self) -> bool:
        return self.reason is Reason.ACCEPTED

    @classmethod
    def of(cls, reason: Reason, detail: str = "") -> Verdict:
        """A verdict whose headline is the reason's own name."""
        return cls(reason, reason.value, detail)

    @classmethod
    def recorded(cls, text: str, accepted: bool) -> Verdict:
        """The verdict a file recorded (pairs.json, the registration cache)."""
        if accepted:
            return cls.of(Reason.ACCEPTED)
        return cls.of(Reason.NOT_REGISTERED) if text == Reason.NOT_REGISTERED.value else cls(Reason.RECORDED, text)


def decide(r: Registration, cfg: IcpConfig, centre: np.ndarray) -> tuple[Verdict, float]:
    """The verdict on registration ``r`` under the gates of ``cfg``, and how far it moves ``centre`` (m)."""
    T = r.target_from_source
    moved = float(np.linalg.norm(T[:3, :3] @ centre + T[:3, 3] - centre))
    angle = float(np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()))
    if r.fitness < cfg.min_fitness:
        return Verdict(Reason.FITNESS, f"fitness {r.fitness:.2f} < {cfg.min_fitness}"), moved
    if r.structure_fitness < cfg.min_structure_fitness:
        return Verdict(
            Reason.STRUCTURE_FITNESS, f"structure fitness {r.structure_fitness:.2f} < {cfg.min_structure_fitness}"
        ), moved
    if not r.rmse_m <= cfg.lambda_icp_m:  # NaN (no correspondence) fails too
        return Verdict(Reason.RMSE, f"RMSE {r.rmse_m:.3f} m > lambda_ICP {cfg.lambda_icp_m} m"), moved
    if not r.structure_rmse_m <= cfg.lambda_icp_m:
        return Verdict(
            Reason.STRUCTURE_RMSE, f"structure RMSE {r.structure_rmse_m:.3f} m > lambda_ICP {cfg.lambda_icp_m} m"
        ), moved
    if moved > cfg.max_correction_m:
        return Verdict(Reason.CORRECTION, f"correction {moved:.1f} m > {cfg.max_correction_m} m"), moved
    if angle > cfg.max_rotation_deg:
        return Verdict(Reason.ROTATION, f"rotation {angle:.1f} deg > {cfg.max_rotation_deg} deg"), moved
    return Verdict.of(Reason.ACCEPTED), moved


# --- submap pairs ----------------------------------------------------------------------------------


@dataclass
class PairResult:
    source: tuple[str, int]
    target: tuple[str, int]
    centre: np.ndarray  # (3,) ENU, where the pair's support points lie
    target_from_source: np.ndarray  # (4, 4): maps source points onto the target's
    verdict: Verdict
    fitness: float
    rmse_m: float
    source_points: int
    target_points: int
    correction_m: float
    seconds: float
    structure_fitness: float = 0.0
    structure_rmse_m: float = float("nan")
    key: str = ""
    map_source: str = "semidense"  # the maps registered: semidense or lidar (AlignConfig.map_source)

    @property
    def accepted(self) -> bool:
        return self.verdict.accepted

    @property
    def reason(self) -> str:
        """The verdict's text, as pairs.json has it."""
        return self.verdict.text

    def registration(self) -> Registration:
        return Registration(
            self.target_from_source, self.fitness, self.rmse_m, self.structure_fitness, self.structure_rmse_m
        )

    def to_dict(self) -> dict:
        return {
            "source": list(self.source),
            "target": list(self.target),
            "centre": self.centre.tolist(),
            "target_from_source": self.target_from_source.tolist(),
            "accepted": self.accepted,
            "reason": self.reason,
            "fitness": self.fitness,
            "structure_fitness": self.structure_fitness,
            "rmse_m": self.rmse_m,
            "structure_rmse_m": self.structure_rmse_m,
            "source_points": self.source_points,
            "target_points": self.target_points,
            "correction_m": self.correction_m,
            "key": self.key,
            "map_source": self.map_source,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PairResult:
        return cls(
            tuple(d["source"]),
            tuple(d["target"]),
            np.asarray(d["centre"]),
            np.asarray(d["target_from_source"]),
            Verdict.recorded(d["reason"], bool(d["accepted"])),
            float(d["fitness"]),
            float(d["rmse_m"]),
            int(d["source_points"]),
            int(d["target_points"]),
            float(d["correction_m"]),
            float(d.get("seconds", 0.0)),
            float(d.get("structure_fitness", 0.0)),
            float(d.get("structure_rmse_m", float("nan"))),
            d.get("key", ""),
            d.get("map_source", "semidense"),
        )


def pair_points(
    a: SessionData | SubmapClouds,
    i: int,
    b: SessionData | SubmapClouds,
    j: int,
    crop_radius_m: float,
    target_neighbours: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points a pair is registered on: submap ``i`` of ``a`` and submap ``j`` of ``b`` with ``target_neighbours``
    submaps on each side, both cropped to ``crop_radius_m`` (in the ground plane) about the pair centre; and that
    centre."""
    centre = 0.5 * (a.centres[i] + b.centres[j])
    src = submap_points(a, i)
    tgt = submap_points(b, j, target_neighbours)
    r2 = crop_radius_m**2
    src = src[np.sum((src[:, :2] - centre[:2]) ** 2, axis=1) < r2]
    tgt = tgt[np.sum((tgt[:, :2] - centre[:2]) ** 2, axis=1) < r2]
    return src, tgt, centre


def enough_points(source_points: int, target_points: int, min_points: int) -> bool:
    """Whether a pair's cropped clouds (:func:`pair_points`) hold enough points on both sides to be registered."""
    return min(source_points, target_points) >= min_points


def register_pair(
    a: SessionData | SubmapClouds,
    i: int,
    b: SessionData | SubmapClouds,
    j: int,
    icp: IcpConfig,
    crop_radius_m: float,
    target_neighbours: int,
    min_points: int,
) -> PairResult:
    """Submap ``i`` of ``a`` registered onto submap ``j`` of ``b`` (with ``target_neighbours``
    submaps on each side), both cropped to ``crop_radius_m`` about the pair centre, and judged."""
    t0 = time.perf_counter()
    src, tgt, centre = pair_points(a, i, b, j, crop_radius_m, target_neighbours)
    base: dict[str, Any] = dict(
        source=(a.name, i), target=(b.name, j), centre=centre, source_points=len(src), target_points=len(tgt)
    )
    if not enough_points(len(src), len(tgt), min_points):
        return PairResult(
            **base,
            target_from_source=np.eye(4),
            verdict=Verdict.of(Reason.NOT_REGISTERED),
            fitness=0.0,
            rmse_m=float("nan"),
            correction_m=0.0,
            seconds=time.perf_counter() - t0,
        )
    r = register_clouds(src, tgt, centre, icp)
    verdict, moved = decide(r, icp, centre)
    return PairResult(
        **base,
        target_from_source=r.target_from_source,
        verdict=verdict,
        fitness=r.fitness,
        rmse_m=r.rmse_m,
        correction_m=moved,
        seconds=time.perf_counter() - t0,
        structure_fitness=r.structure_fitness,
        structure_rmse_m=r.structure_rmse_m,
    )
