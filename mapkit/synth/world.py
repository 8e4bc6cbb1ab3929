"""The procedural town: road graph, road surfaces, buildings, props, and the mesh they make.

Everything is in the world ENU frame (metres, x east, y north, z up) of the town's ``LocalFrame``
and deterministic from the seed. The road surface is at z = 0, the surrounding ground 2 cm below
it, sidewalks 15 cm above it.

Geometry is one triangle soup with per-triangle attributes that the renderer gathers with the
ray-cast primitive ids: a material, an object id, a style, and a texture frame (origin and two
unit axes) in which a hit point has surface coordinates in metres (along and across a road, along
and up a facade). ``aux`` holds eight material-specific numbers (see ``AUX`` below).

Parked cars are not part of the static world: each session draws its own (``parked_cars``).
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from functools import partial
from itertools import pairwise
from pathlib import Path

import numpy as np

from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import atomic_path, atomic_write_text, to_json
from mapkit.synth.config import SynthConfig, TownConfig

ROAD_Z = 0.0
GROUND_Z = -0.02


class Mat(IntEnum):
    SKY = 0
    GROUND = 1
    ROAD = 2
    JUNCTION = 3
    SIDEWALK = 4
    CURB = 5
    WALL = 6
    ROOF = 7
    TRUNK = 8
    FOLIAGE = 9
    POLE = 10
    LAMP = 11
    SIGN = 12
    FENCE = 13
    CAR_BODY = 14
    CAR_GLASS = 15
    CAR_WHEEL = 16
    HILL = 17


#: meaning of the eight ``aux`` numbers per material (the rest are zero)
AUX = {
    Mat.ROAD: (
        "s_at_origin_m",
        "road_length_m",
        "half_width_m",
        "kind",
        "s_start_m",
        "s_end_m",
        "crosswalk_a",
        "crosswalk_b",
    ),
    Mat.SIDEWALK: ("s_at_origin_m",),
    Mat.WALL: ("wall_length_m", "eave_height_m", "floor_height_m", "is_front", "r", "g", "b", "building_hash"),
    Mat.ROOF: ("pitched", "", "", "", "r", "g", "b", "building_hash"),
    Mat.FOLIAGE: ("tree_hash",),
    Mat.SIGN: ("sign_type",),
    Mat.FENCE: ("fence_kind",),
    Mat.CAR_BODY: ("r", "g", "b"),
}

ROAD_KINDS = {"lane": 0, "street": 1, "avenue": 2, "track": 3}


# --- triangle soup with attributes ----------------------------------------------------------------


@dataclass
class Geometry:
    """Triangles and their attributes (all arrays have one row per triangle)."""

    vertices: np.ndarray  # (V, 3) float64, world ENU metres
    triangles: np.ndarray  # (T, 3) int32
    material: np.ndarray  # (T,) uint8 (Mat)
    object_id: np.ndarray  # (T,) int32
    style: np.ndarray  # (T,) int16
    origin: np.ndarray  # (T, 3) float32: texture-frame origin
    axis_u: np.ndarray  # (T, 3) float32: texture-frame first axis (unit)
    axis_v: np.ndarray  # (T, 3) float32: texture-frame second axis (unit)
    aux: np.ndarray  # (T, 8) float32

    @property
    def n_triangles(self) -> int:
        return int(len(self.triangles))

    @staticmethod
    def concat(parts: list[Geometry]) -> Geometry:
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts])[:-1]
        return Geometry(
            np.concatenate([p.vertices for p in parts]) if parts else np.zeros((0, 3)),
            np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=True)]).astype(np.int32)
            if parts
            else np.zeros((0, 3), np.int32),
            *[
                np.concatenate([getattr(p, k) for p in parts])
                for k in ("material", "object_id", "style", "origin", "axis_u", "axis_v", "aux")
            ],
        )


class MeshBuilder:
    """Accumulates triangles with attributes; scalars and single rows broadcast to all triangles."""

    def __init__(self) -> None:
        self.parts: list[Geometry] = []

    def add(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        material,
        *,
        object_id=-1,
        style=0,
        origin=(0.0, 0.0, 0.0),
        axis_u=(1.0, 0.0, 0.0),
        axis_v=(0.0, 1.0, 0.0),
        aux=None,
    ) -> None:
        tris = np.asarray(triangles, np.int32).reshape(-1, 3)
        n = len(tris)
        if n == 0:
            return

        def rows(x, width, dtype):
            a = np.asarray(x, dtype)
            if width is None:
                return np.broadcast_to(a, (n,)).astype(dtype)
            if a.ndim == 1 and a.shape[0] < width:
                a = np.concatenate([a, np.zeros(width - a.shape[0], dtype)])
            elif a.ndim == 2 and a.shape[1] < width:
                a = np.concatenate([a, np.zeros((a.shape[0], width - a.shape[1]), dtype)], axis=1)
            return np.broadcast_to(a, (n, width)).astype(dtype)

        self.parts.append(
            Geometry(
                np.asarray(vertices, np.float64).reshape(-1, 3),
                tris,
                rows(material, None, np.uint8),
                rows(object_id, None, np.int32),
                rows(style, None, np.int16),
                rows(origin, 3, np.float32),
                rows(axis_u, 3, np.float32),
                rows(axis_v, 3, np.float32),
                rows(np.zeros(8) if aux is None else aux, 8, np.float32),
            )
        )

    def build(self) -> Geometry:
        return Geometry.concat(self.parts)


def _orient(vertices: np.ndarray, tris: np.ndarray, want_normal: np.ndarray) -> np.ndarray:
    """Flip the triangles whose winding gives a normal opposite to ``want_normal`` (T, 3)."""
    v = vertices[tris]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", n, want_normal) < 0
    out = tris.copy()
    out[flip] = out[flip][:, [0, 2, 1]]
    return out


# --- boxes (vectorised) ---------------------------------------------------------------------------

# corners of a unit box around the origin of its bottom face: x, y in {-1, 1}, z in {0, 1}
_BOX_CORNERS = np.array(
    [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]], float
)
# walls as quads (bottom-left, bottom-right, top-right, top-left seen from outside): +x, +y, -x, -y; then the top
_BOX_QUADS = np.array([[1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7], [0, 1, 5, 4], [4, 5, 6, 7]])
_BOX_FACE_NORMALS = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, 1]], float)


@dataclass
class Boxes:
    """Boxes standing on z = base_z: centre of the bottom face, half extents in x/y, height, yaw."""

    center: np.ndarray  # (n, 3)
    half_xy: np.ndarray  # (n, 2)
    height: np.ndarray  # (n,)
    yaw: np.ndarray  # (n,)

    def rotations(self) -> np.ndarray:
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        R = np.zeros((len(self.yaw), 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
        return R


def box_faces(b: Boxes, faces: tuple[int, ...] = (0, 1, 2, 3, 4)):
    """Vertices (n*8, 3) and, per requested face, its triangles (n*2, 3), outward normal,
    texture frame (origin = bottom-left corner seen from outside, u along, v up) and face size."""
    n = len(b.height)
    R = b.rotations()
    local = _BOX_CORNERS[None] * np.concatenate([b.half_xy, b.height[:, None]], axis=1)[:, None, :]
    verts = np.einsum("nij,nkj->nki", R, local) + b.center[:, None, :]
    out = []
    base = (np.arange(n) * 8)[:, None]
    for f in faces:
        q = _BOX_QUADS[f]
        tris = np.stack([base + q[[0, 1, 2]], base + q[[0, 2, 3]]], axis=1).reshape(-1, 3)
        normal = np.einsum("nij,j->ni", R, _BOX_FACE_NORMALS[f])
        a, bb, d = verts[:, q[0]], verts[:, q[1]], verts[:, q[3]]
        width = np.linalg.norm(bb - a, axis=1)
        u = (bb - a) / np.maximum(width, 1e-9)[:, None]
        tall = np.linalg.norm(d - a, axis=1)
        v = (d - a) / np.maximum(tall, 1e-9)[:, None]
        out.append(
            dict(
                triangles=tris,
                normal=np.repeat(normal, 2, axis=0),
                origin=np.repeat(a, 2, axis=0),
                axis_u=np.repeat(u, 2, axis=0),
                axis_v=np.repeat(v, 2, axis=0),
                width=width,
                tall=tall,
            )
        )
    return verts.reshape(-1, 3), out


def add_boxes(
    mb: MeshBuilder, b: Boxes, material: Mat | dict, *, object_id=None, style=None, aux=None, faces=(0, 1, 2, 3, 4)
) -> None:
    """Add boxes; ``material`` may map face index to material; per-box arrays repeat per triangle."""
    if len(b.height) == 0:
        return
    verts, fl = box_faces(b, faces)
    n = len(b.height)

    def per(x, default):
        """``x`` per triangle: ``default`` for None, a per-box array repeated (two triangles a face), else as is."""
        return default if x is None else (np.repeat(np.asarray(x), 2, axis=0) if np.ndim(x) >= 1 and len(x) == n else x)

    for f, fd in zip(faces, fl, strict=True):
        mat = material.get(f, material.get("default")) if isinstance(material, dict) else material
        if mat is None:
            continue
        aux_f = aux(f, fd) if callable(aux) else aux
        mb.add(
            verts,
            fd["triangles"],
            mat,
            object_id=per(object_id, -1),
            style=per(style, 0),
            origin=fd["origin"],
            axis_u=fd["axis_u"],
            axis_v=fd["axis_v"],
            aux=per(aux_f, None),
        )


def instances(template_v: np.ndarray, template_t: np.ndarray, pos: np.ndarray, scale: np.ndarray, yaw: np.ndarray):
    """Copies of a template mesh: scaled (n, 3), rotated about z, translated; vertices and triangles."""
    n = len(pos)
    c, s = np.cos(yaw), np.sin(yaw)
    v = template_v[None] * scale[:, None, :]
    x = c[:, None] * v[..., 0] - s[:, None] * v[..., 1]
    y = s[:, None] * v[..., 0] + c[:, None] * v[..., 1]
    verts = np.stack([x, y, v[..., 2]], axis=-1) + pos[:, None, :]
    tris = template_t[None] + (np.arange(n) * len(template_v))[:, None, None]
    return verts.reshape(-1, 3), tris.reshape(-1, 3)


# --- road graph -----------------------------------------------------------------------------------


@dataclass
class Road:
    id: int
    a: int
    b: int
    kind: str
    half_width_m: float
    polyline: np.ndarray  # (M, 2) from node a to node b

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.polyline, axis=0), axis=1).sum())

    def arc(self) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(self.polyline, axis=0), axis=1))])

    def point_at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (n, 2) and unit tangents (n, 2) at arc lengths ``s``."""
        S = self.arc()
        s = np.clip(np.asarray(s, float), 0, S[-1])
        k = np.clip(np.searchsorted(S, s, side="right") - 1, 0, len(S) - 2)
        seg = self.polyline[k + 1] - self.polyline[k]
        L = np.maximum(np.linalg.norm(seg, axis=-1), 1e-9)
        t = seg / L[..., None]
        return self.polyline[k] + t * (s - S[k])[..., None], t


@dataclass
class RoadGraph:
    nodes_xy: np.ndarray  # (N, 2)
    roads: list[Road]
    junction_radius_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (N,) road surface
    sidewalk_radius_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (N,) sidewalks start here

    def incident(self, node: int) -> list[tuple[Road, int]]:
        """(road, other node) pairs at ``node``."""
        return [(r, r.b if r.a == node else r.a) for r in self.roads if r.a == node or r.b == node]

    def degree(self) -> np.ndarray:
        deg = np.zeros(len(self.nodes_xy), int)
        for r in self.roads:
            deg[r.a] += 1
            deg[r.b] += 1
        return deg

    def oriented(self, road: Road, start: int) -> np.ndarray:
        """The road's polyline from ``start`` to its other end."""
        return road.polyline if road.a == start else road.polyline[::-1]

    def to_json(self) -> dict:
        deg = self.degree()
        return {
            "frame": "world ENU (metres)",
            "nodes": [
                {
                    "id": i,
                    "xy": [round(float(x), 4), round(float(y), 4)],
                    "degree": int(deg[i]),
                    "junction_radius_m": round(float(self.junction_radius_m[i]), 3),
                }
                for i, (x, y) in enumerate(self.nodes_xy)
            ],
            "edges": [
                {
                    "id": r.id,
                    "a": r.a,
                    "b": r.b,
                    "kind": r.kind,
                    "half_width_m": r.half_width_m,
                    "length_m": round(r.length_m, 3),
                    "polyline": np.round(r.polyline, 4).tolist(),
                }
                for r in self.roads
            ],
        }

    @classmethod
    def from_json(cls, d: dict) -> RoadGraph:
        nodes = np.array([n["xy"] for n in d["nodes"]], float).reshape(-1, 2)
        roads = [
            Road(e["id"], e["a"], e["b"], e["kind"], float(e["half_width_m"]), np.array(e["polyline"], float))
            for e in d["edges"]
        ]
        g = cls(nodes, roads)
        g.junction_radius_m = np.array([n.get("junction_radius_m", 0.0) for n in d["nodes"]], float)
        return g


def _connected(n_nodes: int, edges: set[tuple[int, int]]) -> bool:
    adj: dict[int, list[int]] = {i: [] for i in range(n_nodes)}
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)
    used = [i for i in range(n_nodes) if adj[i]]
    if not used:
        return True
    seen = {used[0]}
    q = deque([used[0]])
    while q:
        u = q.popleft()
        for w in adj[u]:
            if w not in seen:
                seen.add(w)
                q.append(w)
    return len(seen) == len(used)


@dataclass
class _Lattice:
    """The perturbed lattice a town's road graph starts from: node ``node_id[i, j]`` (column i,
    row j) at ``nodes_xy[node_id[i, j]]``, blocks ``block_m`` apart, and the rows and columns
    that are avenues (straight: no jitter across them)."""

    node_id: np.ndarray  # (nx, ny) int
    nodes_xy: np.ndarray  # (nx ny, 2)
    block_m: tuple[float, float]
    av_rows: list[int]
    av_cols: list[int]

    @property
    def nx(self) -> int:
        return self.node_id.shape[0]

    @property
    def ny(self) -> int:
        return self.node_id.shape[1]


def _lattice(town: TownConfig, rng: np.random.Generator) -> _Lattice:
    """The town's lattice: avenues on interior rows and columns alternately (never adjacent),
    every other node jittered by up to ``town.jitter`` of a block along each free axis."""
    sx, sy = town.size_m
    nx = max(2, int(round(sx / town.block_m)) + 1)
    ny = max(2, int(round(sy / town.block_m)) + 1)
    bx, by = sx / (nx - 1), sy / (ny - 1)
    xs = np.arange(nx) * bx - sx / 2
    ys = np.arange(ny) * by - sy / 2
    av_rows: list[int] = []
    av_cols: list[int] = []
    rows_avail = list(range(1, ny - 1)) or list(range(ny))
    cols_avail = list(range(1, nx - 1)) or list(range(nx))
    for k in range(town.n_avenues):
        pool, dest = (rows_avail, av_rows) if k % 2 == 0 else (cols_avail, av_cols)
        pool = [p for p in pool if p not in dest and all(abs(p - q) > 1 for q in dest)]
        if pool:
            dest.append(int(rng.choice(pool)))
    node_id = -np.ones((nx, ny), int)
    nodes: list[tuple[float, float]] = []
    jit = town.jitter
    for i in range(nx):
        for j in range(ny):
            jx = 0.0 if i in av_cols else rng.uniform(-jit, jit) * bx
            jy = 0.0 if j in av_rows else rng.uniform(-jit, jit) * by
            node_id[i, j] = len(nodes)
            nodes.append((xs[i] + jx, ys[j] + jy))
    return _Lattice(node_id, np.array(nodes, float), (bx, by), av_rows, av_cols)


def _lattice_edges(lat: _Lattice) -> dict[tuple[int, int], str]:
    """Every lattice edge (node pair) and its kind: avenue along an avenue row or column, else street."""
    edges: dict[tuple[int, int], str] = {}
    node_id = lat.node_id
    for i in range(lat.nx):
        for j in range(lat.ny):
            if i + 1 < lat.nx:
                edges[(node_id[i, j], node_id[i + 1, j])] = "avenue" if j in lat.av_rows else "street"
            if j + 1 < lat.ny:
                edges[(node_id[i, j], node_id[i, j + 1])] = "avenue" if i in lat.av_cols else "street"
    return edges


def _degrees(n_nodes: int, edges: dict[tuple[int, int], str]) -> np.ndarray:
    d = np.zeros(n_nodes, int)
    for a, b in edges:
        d[a] += 1
        d[b] += 1
    return d


def _thin_streets(edges: dict[tuple[int, int], str], n_nodes: int, fraction: float, rng: np.random.Generator) -> None:
    """Drop about ``fraction`` of the streets (in random order) where both ends keep more than two
    roads and the graph stays connected (T-junctions)."""
    cand = [e for e, k in edges.items() if k == "street"]
    for idx in rng.permutation(len(cand)):
        e = cand[idx]
        if rng.random() >= fraction:
            continue
        d = _degrees(n_nodes, edges)
        if d[e[0]] <= 2 or d[e[1]] <= 2:
            continue
        rest = set(edges) - {e}
        if _connected(n_nodes, rest):
            del edges[e]


def _angle_ok(
    nodes_xy: np.ndarray, edges: dict[tuple[int, int], str], node: int, direction: np.ndarray, min_deg: float = 38.0
) -> bool:
    """Whether a new road leaving ``node`` along ``direction`` keeps ``min_deg`` from its roads."""
    for a, b in edges:
        if node in (a, b):
            other = b if a == node else a
            d = nodes_xy[other] - nodes_xy[node]
            cosang = float(np.dot(d, direction) / (np.linalg.norm(d) * np.linalg.norm(direction)))
            if cosang > np.cos(np.radians(min_deg)):
                return False
    return True


def _add_diagonals(
    lat: _Lattice, edges: dict[tuple[int, int], str], fraction: float, rng: np.random.Generator
) -> set[tuple[int, int]]:
    """Diagonal streets across about ``fraction`` of the cells (5-way junctions where a node had 4
    roads); returns the cells they cross."""
    node_id, nodes_xy = lat.node_id, lat.nodes_xy
    busy_cells: set[tuple[int, int]] = set()
    for i in range(lat.nx - 1):
        for j in range(lat.ny - 1):
            if rng.random() >= fraction:
                continue
            if rng.random() < 0.5:
                a, b = node_id[i, j], node_id[i + 1, j + 1]
            else:
                a, b = node_id[i + 1, j], node_id[i, j + 1]
            d = _degrees(len(nodes_xy), edges)
            if d[a] > 4 or d[b] > 4:
                continue
            v = nodes_xy[b] - nodes_xy[a]
            if _angle_ok(nodes_xy, edges, a, v) and _angle_ok(nodes_xy, edges, b, -v):
                edges[(a, b)] = "street"
                busy_cells.add((i, j))
    return busy_cells


def _add_dead_ends(
    lat: _Lattice,
    edges: dict[tuple[int, int], str],
    busy_cells: set[tuple[int, int]],
    n_dead_ends: int,
    rng: np.random.Generator,
) -> list[np.ndarray]:
    """Lanes that end: cul-de-sacs from a corner into free cells (marked busy) and stubs out of
    the town edge; returns their tips, the new nodes numbered on from the lattice's."""
    node_id, nodes_xy = lat.node_id, lat.nodes_xy
    nx, ny = lat.nx, lat.ny
    extra_nodes: list[np.ndarray] = []
    n_inner = (n_dead_ends + 1) // 2
    free_cells = [(i, j) for i in range(nx - 1) for j in range(ny - 1) if (i, j) not in busy_cells]
    for k in rng.permutation(len(free_cells))[:n_inner]:
        i, j = free_cells[k]
        corners = [node_id[i, j], node_id[i + 1, j], node_id[i + 1, j + 1], node_id[i, j + 1]]
        centre = nodes_xy[corners].mean(axis=0)
        d = _degrees(len(nodes_xy) + len(extra_nodes), edges)
        choices = [c for c in corners if d[c] <= 4]
        if not choices:
            continue
        c = int(rng.choice(choices))
        v = centre - nodes_xy[c]
        if not _angle_ok(nodes_xy, edges, c, v):
            continue
        tip = nodes_xy[c] + v * rng.uniform(0.55, 0.7)
        extra_nodes.append(tip)
        edges[(c, len(nodes_xy) + len(extra_nodes) - 1)] = "lane"
        busy_cells.add((i, j))
    boundary = [(i, j) for i in range(nx) for j in range(ny) if (i in (0, nx - 1)) != (j in (0, ny - 1))]
    n_outer = n_dead_ends - n_inner
    for k in rng.permutation(len(boundary))[:n_outer]:
        i, j = boundary[k]
        c = node_id[i, j]
        out = np.array(
            [-1.0 if i == 0 else (1.0 if i == nx - 1 else 0.0), -1.0 if j == 0 else (1.0 if j == ny - 1 else 0.0)]
        )
        if _degrees(len(nodes_xy) + len(extra_nodes), edges)[c] > 3:
            continue
        tip = nodes_xy[c] + out * 0.4 * min(lat.block_m)
        extra_nodes.append(tip)
        edges[(c, len(nodes_xy) + len(extra_nodes) - 1)] = "lane"
    return extra_nodes


def _cells_of(node_id: np.ndarray, a: int, b: int) -> list[tuple[int, int]]:
    """The two lattice cells on either side of the lattice edge (a, b)."""
    ia, ja = np.argwhere(node_id == a)[0] if a < node_id.size else (-9, -9)
    ib, jb = np.argwhere(node_id == b)[0] if b < node_id.size else (-9, -9)
    if ja == jb:  # horizontal edge
        return [(min(ia, ib), ja - 1), (min(ia, ib), ja)]
    return [(ia - 1, min(ja, jb)), (ia, min(ja, jb))]


def _roads_of_edges(
    node_id: np.ndarray,
    nodes_xy: np.ndarray,
    edges: dict[tuple[int, int], str],
    busy_cells: set[tuple[int, int]],
    town: TownConfig,
    rng: np.random.Generator,
) -> list[Road]:
    """The roads of the edges in node order: straight, except lattice streets beside no busy cell,
    of which about ``town.curve_fraction`` bend (a bump with zero slope at both ends)."""
    roads: list[Road] = []
    for (a, b), kind in sorted(edges.items()):
        pa, pb = nodes_xy[a], nodes_xy[b]
        lattice = (
            a < node_id.size
            and b < node_id.size
            and abs(np.subtract(*[np.argwhere(node_id == n)[0] for n in (a, b)])).sum() == 1
        )
        poly = np.array([pa, pb])
        if (
            kind == "street"
            and lattice
            and rng.random() < town.curve_fraction
            and not any(c in busy_cells for c in _cells_of(node_id, a, b))
        ):
            f = np.linspace(0, 1, 25)
            L = np.linalg.norm(pb - pa)
            t = (pb - pa) / L
            nrm = np.array([-t[1], t[0]])
            amp = town.curve_amplitude * L * rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0)
            poly = pa + np.outer(f, pb - pa) + np.outer(amp * np.sin(np.pi * f) ** 2, nrm)
        hw = {"avenue": town.avenue_half_width_m, "street": town.street_half_width_m, "lane": town.lane_half_width_m}[
            kind
        ]
        roads.append(Road(len(roads), int(a), int(b), kind, float(hw), poly))
    return roads


def generate_roads(town: TownConfig, rng: np.random.Generator) -> RoadGraph:
    """A perturbed lattice thinned and enriched into a town graph.

    Straight avenues cross the town (no jitter across them); some lattice edges are dropped
    (T-junctions), some cells get a diagonal (5-way junctions), some edges bend, and cul-de-sacs
    and stubs at the town edge make dead ends.
    """
    lat = _lattice(town, rng)
    edges = _lattice_edges(lat)
    _thin_streets(edges, len(lat.nodes_xy), town.drop_edge_fraction, rng)
    busy_cells = _add_diagonals(lat, edges, town.diagonal_fraction, rng)
    extra_nodes = _add_dead_ends(lat, edges, busy_cells, town.n_dead_ends, rng)
    nodes_xy = np.vstack([lat.nodes_xy, np.array(extra_nodes)]) if extra_nodes else lat.nodes_xy
    roads = _roads_of_edges(lat.node_id, nodes_xy, edges, busy_cells, town, rng)
    g = RoadGraph(nodes_xy, roads)
    compute_junction_radii(g, town.sidewalk_width_m)
    return g


def compute_junction_radii(g: RoadGraph, sidewalk_width_m: float) -> None:
    """Where road strips and sidewalks stop before a node so that neighbouring ones never overlap."""
    n = len(g.nodes_xy)
    r_road = np.zeros(n)
    r_side = np.zeros(n)
    for node in range(n):
        inc = g.incident(node)
        if not inc:
            continue
        if len(inc) == 1:
            w = inc[0][0].half_width_m
            r_road[node] = r_side[node] = 1.5 * w  # cul-de-sac bulb
            continue
        dirs, widths, lengths = [], [], []
        for road, _ in inc:
            p = g.oriented(road, node)
            d = p[1] - p[0]
            dirs.append(np.arctan2(d[1], d[0]))
            widths.append(road.half_width_m)
            lengths.append(road.length_m)
        order = np.argsort(dirs)
        ang = np.array(dirs)[order]
        wid = np.array(widths)[order]
        gaps = np.diff(np.concatenate([ang, [ang[0] + 2 * np.pi]]))
        rr, rs = 1.0, 1.0
        for k, gap in enumerate(gaps):
            if gap >= np.pi - 1e-6:
                continue
            w = max(wid[k], wid[(k + 1) % len(wid)])
            t = np.tan(gap / 2)
            rr = max(rr, w / t + 1.0)
            rs = max(rs, (w + sidewalk_width_m) / t + 0.5)
        cap = 0.4 * min(lengths)
        r_road[node] = min(rr, cap)
        r_side[node] = min(max(rs, r_road[node]), cap)
    g.junction_radius_m = r_road
    g.sidewalk_radius_m = r_side


# --- road surfaces --------------------------------------------------------------------------------


def _resample(poly: np.ndarray, s0: float, s1: float, max_step: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Points of a polyline between arc lengths s0 and s1 (its own vertices kept), and their s."""
    S = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    inner = S[(s0 < S) & (s1 > S)]
    s = np.concatenate([[s0], inner, [s1]])
    # always densify: long thin triangles (a 50 m kerb face is 0.15 m tall) hurt ray and distance queries
    s = np.unique(np.concatenate([s, np.linspace(s0, s1, max(2, int(np.ceil((s1 - s0) / max_step)) + 1))]))
    x = np.interp(s, S, poly[:, 0])
    y = np.interp(s, S, poly[:, 1])
    return np.stack([x, y], axis=1), s


def _strip(
    mb: MeshBuilder,
    pts: np.ndarray,
    s: np.ndarray,
    lat0: float,
    lat1: float,
    z: float,
    material: Mat,
    aux_fn,
    object_id: int = -1,
    normal_sign: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A horizontal strip between lateral offsets lat0 < lat1 along a polyline (mitred joints)."""
    d = np.gradient(pts, axis=0)
    t = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    nrm = np.stack([-t[:, 1], t[:, 0]], axis=1)
    # mitre: scale the offset so that strips keep their width at bends
    seg = np.diff(pts, axis=0)
    seg_t = seg / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9)
    seg_n = np.stack([-seg_t[:, 1], seg_t[:, 0]], axis=1)
    cosm = np.ones(len(pts))
    cosm[1:-1] = np.clip(np.einsum("ij,ij->i", nrm[1:-1], seg_n[:-1]), 0.5, 1.0)
    left = pts + nrm * (lat1 / cosm)[:, None]
    right = pts + nrm * (lat0 / cosm)[:, None]
    m = len(pts)
    V = np.zeros((2 * m, 3))
    V[:m, :2], V[m:, :2] = right, left
    V[:, 2] = z
    k = np.arange(m - 1)
    tris = np.concatenate([np.stack([k, k + 1, m + k + 1], 1), np.stack([k, m + k + 1, m + k], 1)])
    tris = _orient(V, tris, np.tile([0, 0, normal_sign], (len(tris), 1)))
    seg_idx = np.concatenate([k, k])
    origin = np.concatenate([pts[seg_idx], np.full((len(seg_idx), 1), z)], axis=1)
    u = np.concatenate([seg_t[seg_idx], np.zeros((len(seg_idx), 1))], axis=1)
    v = np.concatenate([seg_n[seg_idx], np.zeros((len(seg_idx), 1))], axis=1)
    mb.add(V, tris, material, object_id=object_id, origin=origin, axis_u=u, axis_v=v, aux=aux_fn(s[seg_idx]))
    return left, right


def _wall_strip(mb: MeshBuilder, line: np.ndarray, z0: float, z1: float, facing: np.ndarray, material: Mat) -> None:
    """Vertical quads along a polyline ``line`` (m, 2) from z0 to z1, facing ``facing`` (m-1, 2)."""
    m = len(line)
    if m < 2:
        return
    V = np.zeros((2 * m, 3))
    V[:m, :2] = line
    V[m:, :2] = line
    V[:m, 2], V[m:, 2] = z0, z1
    k = np.arange(m - 1)
    tris = np.concatenate([np.stack([k, k + 1, m + k + 1], 1), np.stack([k, m + k + 1, m + k], 1)])
    f3 = np.concatenate([facing, np.zeros((len(facing), 1))], axis=1)
    tris = _orient(V, tris, np.concatenate([f3, f3]))
    seg = np.diff(line, axis=0)
    u = np.concatenate(
        [seg / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9), np.zeros((m - 1, 1))], axis=1
    )
    origin = np.concatenate([line[:-1], np.full((m - 1, 1), z0)], axis=1)
    mb.add(V, tris, material, origin=np.concatenate([origin, origin]), axis_u=np.concatenate([u, u]), axis_v=(0, 0, 1))


def _road_aux(ss: np.ndarray, constants: tuple[float, ...]) -> np.ndarray:
    """Per-triangle road attributes: arc length ``ss`` and, broadcast to it, the road's length, half
    width, kind, usable start and end, and whether each end meets a junction."""
    return np.stack([ss, *(np.full_like(ss, c) for c in constants)], 1)


def road_surfaces(mb: MeshBuilder, g: RoadGraph, town: TownConfig) -> None:
    deg = g.degree()
    h = town.sidewalk_height_m
    sw = town.sidewalk_width_m
    for road in g.roads:
        L = road.length_m
        w = road.half_width_m
        s0, s1 = g.junction_radius_m[road.a], L - g.junction_radius_m[road.b]
        if s1 - s0 < 0.5:
            continue
        pts, s = _resample(road.polyline, s0, s1)
        kind = ROAD_KINDS[road.kind]
        xa, xb = float(deg[road.a] >= 3), float(deg[road.b] >= 3)
        _strip(
            mb,
            pts,
            s,
            -w,
            w,
            ROAD_Z,
            Mat.ROAD,
            partial(_road_aux, constants=(L, w, kind, s0, s1, xa, xb)),
            object_id=road.id,
        )
        # sidewalks on both sides, with a curb face toward the road and a low face toward the ground
        q0, q1 = g.sidewalk_radius_m[road.a], L - g.sidewalk_radius_m[road.b]
        if q1 - q0 < 1.0:
            continue
        pts, s = _resample(road.polyline, q0, q1)
        for side in (-1.0, 1.0):
            lat0, lat1 = sorted((side * w, side * (w + sw)))
            left, right = _strip(mb, pts, s, lat0, lat1, h, Mat.SIDEWALK, lambda ss: ss[:, None], object_id=road.id)
            inner, outer = (right, left) if side > 0 else (left, right)
            seg = np.diff(pts, axis=0)
            nrm = np.stack([-seg[:, 1], seg[:, 0]], 1) / np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9)
            _wall_strip(mb, inner, ROAD_Z, h, -side * nrm, Mat.CURB)
            _wall_strip(mb, outer, GROUND_Z, h, side * nrm, Mat.CURB)
            for end, sgn in ((0, -1.0), (-1, 1.0)):
                cap = np.array([inner[end], outer[end]])
                t = pts[1] - pts[0] if end == 0 else pts[-1] - pts[-2]
                t = t / max(np.linalg.norm(t), 1e-9)
                _wall_strip(mb, cap, GROUND_Z, h, (sgn * t)[None], Mat.CURB)
    # junction patches: convex hull of the road ends and a disc, as a fan
    for node in range(len(g.nodes_xy)):
        inc = g.incident(node)
        if not inc:
            continue
        c = g.nodes_xy[node]
        r = g.junction_radius_m[node]
        # a round patch of the widest road's half width (the whole bulb at a dead end)
        r_disc = r if len(inc) == 1 else min(r, max(rd.half_width_m for rd, _ in inc))
        outline = [
            c + r_disc * np.stack([np.cos(a), np.sin(a)], -1) for a in np.linspace(0, 2 * np.pi, 24, endpoint=False)
        ]
        for road, _ in inc:
            p = g.oriented(road, node)
            S = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
            x = np.array([np.interp(r, S, p[:, 0]), np.interp(r, S, p[:, 1])])
            k = min(np.searchsorted(S, r, side="right") - 1, len(p) - 2)
            t = (p[k + 1] - p[k]) / max(np.linalg.norm(p[k + 1] - p[k]), 1e-9)
            nrm = np.array([-t[1], t[0]])
            outline += [x + nrm * road.half_width_m, x - nrm * road.half_width_m]
        hull = _convex_hull(np.array(outline))
        m = len(hull)
        V = np.zeros((m + 1, 3))
        V[0, :2] = hull.mean(axis=0)
        V[1:, :2] = hull
        V[:, 2] = ROAD_Z
        k = np.arange(m)
        tris = np.stack([np.zeros(m, int), 1 + k, 1 + (k + 1) % m], 1)
        tris = _orient(V, tris, np.tile([0, 0, 1.0], (m, 1)))
        mb.add(V, tris, Mat.JUNCTION, object_id=node, origin=(0, 0, ROAD_Z))


def _convex_hull(p: np.ndarray) -> np.ndarray:
    """Counter-clockwise hull of 2D points (monotone chain)."""
    pts = sorted(set(map(tuple, np.round(p, 6))))
    if len(pts) <= 2:
        return np.array(pts)

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, ...]] = []
    upper: list[tuple[float, ...]] = []
    for q in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0:
            lower.pop()
        lower.append(q)
    for q in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0:
            upper.pop()
        upper.append(q)
    return np.array(lower[:-1] + upper[:-1])


# --- occupancy (what is already built on) ---------------------------------------------------------


class Occupancy:
    """A 0.5 m grid over the town: 0 free, -1 road or sidewalk, k > 0 building/prop k."""

    def __init__(self, half_extent: tuple[float, float], res: float = 0.5):
        self.res = res
        self.x0, self.y0 = -half_extent[0], -half_extent[1]
        self.nx = int(np.ceil(2 * half_extent[0] / res))
        self.ny = int(np.ceil(2 * half_extent[1] / res))
        self.grid = np.zeros((self.nx, self.ny), np.int32)

    def _window(self, lo: np.ndarray, hi: np.ndarray):
        i0 = max(0, int(np.floor((lo[0] - self.x0) / self.res)))
        j0 = max(0, int(np.floor((lo[1] - self.y0) / self.res)))
        i1 = min(self.nx, int(np.ceil((hi[0] - self.x0) / self.res)) + 1)
        j1 = min(self.ny, int(np.ceil((hi[1] - self.y0) / self.res)) + 1)
        if i1 <= i0 or j1 <= j0:
            return None
        xi = self.x0 + (np.arange(i0, i1) + 0.5) * self.res
        yj = self.y0 + (np.arange(j0, j1) + 0.5) * self.res
        X, Y = np.meshgrid(xi, yj, indexing="ij")
        return (slice(i0, i1), slice(j0, j1)), X, Y

    def mark_segment(self, a: np.ndarray, b: np.ndarray, radius: float, value: int = -1) -> None:
        w = self._window(np.minimum(a, b) - radius, np.maximum(a, b) + radius)
        if w is None:
            return
        sl, X, Y = w
        d = b - a
        L2 = max(float(d @ d), 1e-12)
        t = np.clip(((X - a[0]) * d[0] + (Y - a[1]) * d[1]) / L2, 0, 1)
        dist2 = (X - a[0] - t * d[0]) ** 2 + (Y - a[1] - t * d[1]) ** 2
        sub = self.grid[sl]
        sub[dist2 <= radius * radius] = value

    def _rect_cells(self, center, half, yaw, grow=0.0):
        c, s = np.cos(yaw), np.sin(yaw)
        ext = np.abs(np.array([[c, -s], [s, c]])) @ (np.asarray(half) + grow)
        w = self._window(center - ext, center + ext)
        if w is None:
            return None
        sl, X, Y = w
        dx, dy = X - center[0], Y - center[1]
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        inside = (np.abs(lx) <= half[0] + grow) & (np.abs(ly) <= half[1] + grow)
        return sl, inside

    def rect_free(self, center, half, yaw, grow=0.3, allow: int = 0) -> bool:
        """Whether a rectangle (grown by ``grow``) covers only free cells (or cells of ``allow``)."""
        r = self._rect_cells(center, half, yaw, grow)
        if r is None:
            return False
        sl, inside = r
        if not inside.any():
            return False
        cells = self.grid[sl][inside]
        return bool(np.all((cells == 0) | (cells == allow)))

    def mark_rect(self, center, half, yaw, value: int) -> None:
        r = self._rect_cells(center, half, yaw)
        if r is None:
            return
        sl, inside = r
        sub = self.grid[sl]
        sub[inside] = value

    def free_at(self, xy: np.ndarray, radius: float = 0.0) -> np.ndarray:
        """Whether points (n, 2) are on free cells (and all cells within ``radius``)."""
        ok = np.ones(len(xy), bool)
        offs = [(0.0, 0.0)] if radius <= 0 else [(dx, dy) for dx in (-radius, 0, radius) for dy in (-radius, 0, radius)]
        for dx, dy in offs:
            i = np.floor((xy[:, 0] + dx - self.x0) / self.res).astype(int)
            j = np.floor((xy[:, 1] + dy - self.y0) / self.res).astype(int)
            inside = (i >= 0) & (i < self.nx) & (j >= 0) & (j < self.ny)
            ok &= inside
            ok[inside] &= self.grid[i[inside], j[inside]] == 0
        return ok


# --- building styles ------------------------------------------------------------------------------

PATTERNS = ("brick", "panel", "plaster", "stone", "glass", "siding")


def building_styles(n: int, rng: np.random.Generator) -> np.ndarray:
    """A table of facade styles, one row per style (columns in ``STYLE_COLUMNS``)."""
    palettes = {
        "brick": [(0.45, 0.2, 0.13), (0.55, 0.3, 0.2), (0.38, 0.18, 0.15), (0.6, 0.45, 0.3)],
        "panel": [(0.6, 0.6, 0.58), (0.45, 0.5, 0.55), (0.7, 0.66, 0.55), (0.35, 0.37, 0.4)],
        "plaster": [(0.8, 0.75, 0.6), (0.75, 0.55, 0.45), (0.85, 0.85, 0.8), (0.6, 0.7, 0.75), (0.8, 0.65, 0.35)],
        "stone": [(0.72, 0.64, 0.48), (0.6, 0.58, 0.55)],
        "glass": [(0.25, 0.35, 0.45), (0.3, 0.38, 0.35)],
        "siding": [(0.85, 0.85, 0.85), (0.55, 0.65, 0.7), (0.7, 0.75, 0.6)],
    }
    rows = []
    for k in range(n):
        pattern = PATTERNS[k % len(PATTERNS)] if k < len(PATTERNS) else PATTERNS[int(rng.integers(len(PATTERNS)))]
        pal = palettes[pattern]
        col = np.array(pal[int(rng.integers(len(pal)))]) * rng.uniform(0.9, 1.1)
        floor_h = rng.uniform(2.9, 3.8)
        spacing = rng.uniform(2.2, 4.2) if pattern != "glass" else rng.uniform(1.4, 1.9)
        win_w = spacing * (rng.uniform(0.35, 0.6) if pattern != "glass" else 0.92)
        win_h = floor_h * (rng.uniform(0.4, 0.6) if pattern != "glass" else 0.8)
        frame = rng.choice([0.9, 0.15, 0.5]) * np.ones(3) * rng.uniform(0.8, 1.0)
        shop = float(rng.random() < 0.55)
        roof = np.array([(0.35, 0.17, 0.12), (0.22, 0.23, 0.26), (0.42, 0.3, 0.22)][int(rng.integers(3))])
        sign_hue = rng.uniform(0, 1)
        rows.append(
            [
                PATTERNS.index(pattern),
                *col,
                floor_h,
                spacing,
                win_w,
                win_h,
                *frame,
                shop,
                *roof,
                sign_hue,
                rng.uniform(0.2, 0.5),
            ]
        )
    return np.array(rows, np.float32)


STYLE_COLUMNS = (
    "pattern",
    "r",
    "g",
    "b",
    "floor_h",
    "spacing",
    "win_w",
    "win_h",
    "frame_r",
    "frame_g",
    "frame_b",
    "shop",
    "roof_r",
    "roof_g",
    "roof_b",
    "sign_hue",
    "lit_fraction",
)


@dataclass
class Town:
    """The generated world: static geometry with attributes, and what sessions and lights need."""

    config: SynthConfig
    frame: LocalFrame
    roads: RoadGraph
    geometry: Geometry
    styles: np.ndarray
    lamps_xyz: np.ndarray  # (L, 3) light positions (lamp heads)
    parking_slots: np.ndarray  # (S, 4): x, y, yaw (car heading), half-width of the lane it parks in
    n_buildings: int
    n_trees: int
    extent_m: tuple[float, float]  # half extents (x, y) of the built area
    anchor: dict  # a place every session passes: road id, start node, s, xy, heading

    def summary(self) -> dict:
        deg = self.roads.degree()
        counts = {int(k): int((deg == k).sum()) for k in np.unique(deg)}
        mats = np.bincount(self.geometry.material, minlength=len(Mat))
        return {
            "triangles": self.geometry.n_triangles,
            "nodes": int(len(deg)),
            "roads": len(self.roads.roads),
            "road_length_m": round(sum(r.length_m for r in self.roads.roads), 1),
            "node_degree_histogram": counts,
            "dead_ends": int((deg == 1).sum()),
            "curved_roads": int(sum(len(r.polyline) > 2 for r in self.roads.roads)),
            "longest_straight_m": round(longest_straight_m(self.roads), 1),
            "buildings": self.n_buildings,
            "building_styles": int(len(self.styles)),
            "trees": self.n_trees,
            "street_lamps": int(len(self.lamps_xyz)),
            "parking_slots": int(len(self.parking_slots)),
            "triangles_by_material": {Mat(k).name.lower(): int(c) for k, c in enumerate(mats) if c},
            "extent_m": [round(2 * e, 1) for e in self.extent_m],
        }


def longest_straight_m(g: RoadGraph) -> float:
    """Longest chain of collinear straight roads through degree >= 2 nodes (an avenue)."""
    best = 0.0
    straight = {r.id: r for r in g.roads if len(r.polyline) == 2}
    for r in straight.values():
        d = r.polyline[-1] - r.polyline[0]
        d = d / np.linalg.norm(d)
        total = r.length_m
        for start, sign in ((r.b, 1.0), (r.a, -1.0)):
            node, prev = start, r.id
            while True:
                nxt = None
                for road, other in g.incident(node):
                    if road.id == prev or road.id not in straight:
                        continue
                    e = g.oriented(road, node)
                    v = (e[-1] - e[0]) / road.length_m
                    if float(v @ (sign * d)) > 0.9995:
                        nxt = (road, other)
                        break
                if nxt is None:
                    break
                total += nxt[0].length_m
                prev, node = nxt[0].id, nxt[1]
        best = max(best, total)
    return best


# --- props ----------------------------------------------------------------------------------------


def _tree_templates(rng: np.random.Generator, n_variants: int = 4):
    import open3d as o3d

    ico = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_loop(1)
    V0 = np.asarray(ico.vertices)
    V0 = V0 / np.linalg.norm(V0, axis=1, keepdims=True)
    T0 = np.asarray(ico.triangles)
    canopies = [V0 * rng.uniform(0.82, 1.15, (len(V0), 1)) for _ in range(n_variants)]
    k = 6
    ang = np.arange(k) * 2 * np.pi / k
    ring = np.stack([np.cos(ang), np.sin(ang)], 1)
    TV = np.concatenate([np.c_[ring, np.zeros(k)], np.c_[ring, np.ones(k)]])
    i = np.arange(k)
    TT = np.concatenate([np.stack([i, (i + 1) % k, k + (i + 1) % k], 1), np.stack([i, k + (i + 1) % k, k + i], 1)])
    return canopies, T0, TV, TT


def _outward(V: np.ndarray, T: np.ndarray, centres: np.ndarray) -> np.ndarray:
    c = V[T].mean(axis=1)
    return _orient(V, T, c - centres)


def build_town(cfg: SynthConfig, trajectory_xy: np.ndarray | None = None) -> Town:
    """Generate the whole town from ``cfg.seed`` (and around an external path, if given)."""
    town = cfg.town
    ss = np.random.SeedSequence([cfg.seed, 0x70_77_4E])
    r_roads, r_build, r_props, r_styles, r_hills = (np.random.default_rng(s) for s in ss.spawn(5))
    g = roads_around_path(town, trajectory_xy, r_roads) if trajectory_xy is not None else generate_roads(town, r_roads)
    lo = np.min(np.vstack([g.nodes_xy] + [r.polyline for r in g.roads]), axis=0)
    hi = np.max(np.vstack([g.nodes_xy] + [r.polyline for r in g.roads]), axis=0)
    half = np.maximum(np.abs(lo), np.abs(hi)) + 40.0
    occ = Occupancy((float(half[0]), float(half[1])))
    for road in g.roads:
        w = road.half_width_m + town.sidewalk_width_m + 0.3
        for a, b in pairwise(road.polyline):
            occ.mark_segment(a, b, w)
    for node in range(len(g.nodes_xy)):
        occ.mark_segment(g.nodes_xy[node], g.nodes_xy[node], g.sidewalk_radius_m[node] + town.sidewalk_width_m)

    mb = MeshBuilder()
    road_surfaces(mb, g, town)
    styles = building_styles(town.buildings.n_styles, r_styles)
    n_buildings, fences = _buildings(mb, g, town, styles, occ, r_build)
    lamps, n_trees, slots = _props(mb, g, town, occ, fences, r_props)
    _ground_and_hills(mb, half, town.margin_m, r_hills)
    geom = mb.build()
    frame = LocalFrame(cfg.origin.lat_deg, cfg.origin.lon_deg, cfg.origin.alt_m)
    anchor = choose_anchor(g)
    return Town(
        cfg, frame, g, geom, styles, lamps, slots, n_buildings, n_trees, (float(half[0]), float(half[1])), anchor
    )


def choose_anchor(g: RoadGraph) -> dict:
    """A road near the centre with junctions at both ends: every planned route drives it a -> b."""
    deg = g.degree()
    best, best_d = None, np.inf
    for r in g.roads:
        if r.kind == "lane" or deg[r.a] < 3 or deg[r.b] < 3 or r.length_m < 50:
            continue
        mid, _ = r.point_at(np.array([0.5 * r.length_m]))
        d = float(np.linalg.norm(mid[0]))
        if d < best_d:
            best, best_d = r, d
    if best is None:
        best = max(g.roads, key=lambda r: r.length_m)
    s = 0.45 * best.length_m
    xy, t = best.point_at(np.array([s]))
    return {
        "road": best.id,
        "from_node": best.a,
        "to_node": best.b,
        "s_m": round(s, 3),
        "xy": [float(xy[0, 0]), float(xy[0, 1])],
        "heading_rad": float(np.arctan2(t[0, 1], t[0, 0])),
    }


def _buildings(
    mb: MeshBuilder, g: RoadGraph, town: TownConfig, styles: np.ndarray, occ: Occupancy, rng: np.random.Generator
) -> tuple[int, list]:
    """Buildings along both sides of every road, marked in ``occ``, and their meshes; returns the
    number of buildings and the fences of lot gaps (road, side, s from, s to)."""
    boxes: list[tuple] = []  # (center xy, half (2,), yaw, height, style, building id, pitched, front face index)
    fences: list[tuple[Road, float, float, float]] = []  # (road, side, s from, s to)
    bid = 0
    for road in g.roads:
        s_lo = g.sidewalk_radius_m[road.a] + 1.0
        s_hi = road.length_m - g.sidewalk_radius_m[road.b] - 1.0
        for side in (-1.0, 1.0):
            street_styles = rng.choice(len(styles), size=2, replace=len(styles) < 2)
            lots, gaps = _street_side_buildings(road, side, (s_lo, s_hi), street_styles, town, styles, occ, rng, bid)
            boxes += lots
            fences += gaps
            bid = lots[-1][5] if lots else bid
    if not boxes:
        return 0, fences
    return _building_meshes(mb, boxes, styles), fences


def _street_side_buildings(
    road: Road,
    side: float,
    span: tuple[float, float],
    street_styles: np.ndarray,
    town: TownConfig,
    styles: np.ndarray,
    occ: Occupancy,
    rng: np.random.Generator,
    last_id: int,
) -> tuple[list[tuple], list[tuple[Road, float, float, float]]]:
    """Lots along one side of ``road`` between arc lengths ``span``: gaps (some fenced) and
    buildings (mostly in the street's first style, some with a wing behind), each where ``occ``
    is free (marked there), shallower where it is not. Returns their boxes (as :func:`_buildings`
    lists them; building ids count on from ``last_id``) and fences."""
    bc = town.buildings
    s_lo, s_hi = span
    bid = last_id
    boxes: list[tuple] = []
    fences: list[tuple[Road, float, float, float]] = []
    s = s_lo + rng.uniform(0, 3)
    while s < s_hi - bc.frontage_m[0]:
        if rng.random() < bc.gap_probability:
            gap = rng.uniform(4.0, 12.0)
            if rng.random() < town.fence_probability and s + gap < s_hi:
                fences.append((road, side, s, s + gap))
            s += gap
            continue
        f = rng.uniform(*bc.frontage_m)
        if s + f > s_hi:
            f = s_hi - s
            if f < bc.frontage_m[0]:
                break
        d = rng.uniform(*bc.depth_m)
        setback = rng.uniform(*bc.setback_m)
        mid = s + f / 2
        p, t = road.point_at(np.array([mid]))
        p, t = p[0], t[0]
        n_left = np.array([-t[1], t[0]])
        n_away = side * n_left
        off = road.half_width_m + town.sidewalk_width_m + setback
        centre = p + n_away * (off + d / 2)
        x_axis = t if side > 0 else -t
        yaw_rad = float(np.arctan2(x_axis[1], x_axis[0]))
        half = np.array([f / 2, d / 2])
        style_id = int(street_styles[0] if rng.random() < 0.7 else rng.integers(len(styles)))
        floors = int(rng.integers(bc.floors[0], bc.floors[1] + 1))
        floor_h = float(styles[style_id, 4])
        height_m = floors * floor_h + rng.uniform(0.3, 0.8)
        if not occ.rect_free(centre, half, yaw_rad):
            # a shallower building, else move on a little and try again
            d = max(bc.depth_m[0] * 0.75, d * 0.6)
            centre = p + n_away * (off + d / 2)
            half = np.array([f / 2, d / 2])
            if not occ.rect_free(centre, half, yaw_rad):
                s += 3.0
                continue
        bid += 1
        occ.mark_rect(centre, half, yaw_rad, bid)
        pitched_roof = float(rng.random() < bc.pitched_roof_probability and floors <= 4)
        boxes.append((centre, half, yaw_rad, height_m, style_id, bid, pitched_roof, 3))
        if rng.random() < bc.wing_probability:
            fw = f * rng.uniform(0.35, 0.65)
            dw = rng.uniform(5.0, 10.0)
            shift = (f / 2 - fw / 2) * rng.choice([-1.0, 1.0])
            wc = centre + x_axis * shift + n_away * (d / 2 + dw / 2 - 0.5)
            wh = max(floor_h + 0.5, height_m + rng.choice([-1.0, 1.0]) * floor_h * rng.integers(1, 3))
            if occ.rect_free(wc, np.array([fw / 2, dw / 2]), yaw_rad, allow=bid):
                occ.mark_rect(wc, np.array([fw / 2, dw / 2]), yaw_rad, bid)
                boxes.append((wc, np.array([fw / 2, dw / 2]), yaw_rad, wh, style_id, bid, 0.0, -1))
        s += f + rng.uniform(0.0, 1.5)
    return boxes, fences


def _building_meshes(mb: MeshBuilder, boxes: list[tuple], styles: np.ndarray) -> int:
    """Walls, flat roofs and pitched roofs (with gables) of the building boxes, with per-building
    colour jitter and hash; returns the number of buildings."""
    centre = np.array([np.r_[b[0], GROUND_Z] for b in boxes])
    half = np.array([b[1] for b in boxes])
    yaw = np.array([b[2] for b in boxes])
    height = np.array([b[3] for b in boxes])
    style = np.array([b[4] for b in boxes])
    bids = np.array([b[5] for b in boxes])
    pitched = np.array([b[6] for b in boxes]) > 0
    front = np.array([b[7] for b in boxes])
    # per-building colour jitter and hash
    bh = ((bids * 2654435761) % 1000003) / 1000003.0
    tint = 0.88 + 0.24 * ((bids * 40503) % 997) / 997.0
    col = styles[style, 1:4] * tint[:, None]
    roof_pitch = 0.55 * np.minimum(half[:, 0], half[:, 1])  # ridge height above the eave
    eave = height - np.where(pitched, roof_pitch, 0.0)

    def wall_aux(f, fd):
        L = fd["width"]
        return np.stack([L, eave, styles[style, 4], (front == f).astype(float), col[:, 0], col[:, 1], col[:, 2], bh], 1)

    b = Boxes(centre, half, height=eave - GROUND_Z, yaw=yaw)
    add_boxes(
        mb,
        b,
        {0: Mat.WALL, 1: Mat.WALL, 2: Mat.WALL, 3: Mat.WALL},
        object_id=bids,
        style=style,
        aux=wall_aux,
        faces=(0, 1, 2, 3),
    )
    roof_col = styles[style, 12:15]
    flat = ~pitched
    if flat.any():
        bf = Boxes(centre[flat], half[flat], height=eave[flat] - GROUND_Z, yaw=yaw[flat])
        flat_aux = np.zeros((int(flat.sum()), 8))
        flat_aux[:, 4:7] = np.array([0.32, 0.31, 0.30]) * tint[flat, None]
        flat_aux[:, 7] = bh[flat]
        add_boxes(mb, bf, Mat.ROOF, object_id=bids[flat], style=style[flat], aux=flat_aux, faces=(4,))
    if pitched.any():
        _pitched_roofs(
            mb,
            centre[pitched],
            half[pitched],
            yaw[pitched],
            eave[pitched],
            roof_pitch[pitched],
            bids[pitched],
            style[pitched],
            roof_col[pitched],
            bh[pitched],
            col[pitched],
            styles,
        )
    return int(len(np.unique(bids)))


def _pitched_roofs(mb, centre, half, yaw, eave, rise, bids, style, roof_col, bh, wall_col, styles) -> None:
    n = len(eave)
    c, s = np.cos(yaw), np.sin(yaw)
    ex = np.stack([c, s, np.zeros(n)], 1)
    ey = np.stack([-s, c, np.zeros(n)], 1)
    base = centre.copy()
    base[:, 2] = eave
    hx, hy = half[:, 0:1], half[:, 1:2]
    p = lambda a, b, z=0.0: base + ex * (a * hx) + ey * (b * hy) + np.array([0, 0, 1.0]) * z  # noqa: E731 (a one-line helper local to this function)
    # eave corners 0..3, ridge ends 4, 5
    V = np.stack(
        [
            p(-1, -1),
            p(1, -1),
            p(1, 1),
            p(-1, 1),
            p(-1, 0) + np.c_[0 * rise, 0 * rise, rise],
            p(1, 0) + np.c_[0 * rise, 0 * rise, rise],
        ],
        1,
    )
    off = (np.arange(n) * 6)[:, None]
    slopes = np.concatenate(
        [
            np.stack([off[:, 0] + 0, off[:, 0] + 1, off[:, 0] + 5], 1),
            np.stack([off[:, 0] + 0, off[:, 0] + 5, off[:, 0] + 4], 1),
            np.stack([off[:, 0] + 2, off[:, 0] + 3, off[:, 0] + 4], 1),
            np.stack([off[:, 0] + 2, off[:, 0] + 4, off[:, 0] + 5], 1),
        ]
    )
    Vf = V.reshape(-1, 3)
    slopes = _orient(Vf, slopes, np.tile(np.array([0, 0, 1.0]), (len(slopes), 1)))
    idx4 = np.concatenate([np.arange(n)] * 4)
    # texture frame: u along the ridge, v up the slope
    front_mid = (V[:, 0] + V[:, 1]) / 2
    back_mid = (V[:, 2] + V[:, 3]) / 2
    ridge_mid = (V[:, 4] + V[:, 5]) / 2
    v_front = ridge_mid - front_mid
    v_back = ridge_mid - back_mid
    v_front /= np.linalg.norm(v_front, axis=1, keepdims=True)
    v_back /= np.linalg.norm(v_back, axis=1, keepdims=True)
    axis_v = np.concatenate([v_front, v_front, v_back, v_back])
    origin = np.concatenate([V[:, 0], V[:, 0], V[:, 2], V[:, 2]])
    axis_u = np.concatenate([ex, ex, -ex, -ex])
    aux = np.stack([np.ones(n), 0 * bh, 0 * bh, 0 * bh, roof_col[:, 0], roof_col[:, 1], roof_col[:, 2], bh], 1)[idx4]
    mb.add(
        Vf,
        slopes,
        Mat.ROOF,
        object_id=bids[idx4],
        style=style[idx4],
        origin=origin,
        axis_u=axis_u,
        axis_v=axis_v,
        aux=aux,
    )
    # gables: wall material, facade frame continuing the walls below (v up)
    gables = np.concatenate(
        [
            np.stack([off[:, 0] + 1, off[:, 0] + 2, off[:, 0] + 5], 1),
            np.stack([off[:, 0] + 3, off[:, 0] + 0, off[:, 0] + 4], 1),
        ]
    )
    want = np.concatenate([ex, -ex])
    gables = _orient(Vf, gables, want)
    idx2 = np.concatenate([np.arange(n)] * 2)
    g_origin = np.concatenate([V[:, 1], V[:, 3]]).copy()
    g_origin[:, 2] = centre[idx2, 2]
    g_u = np.concatenate([ey, -ey])
    L = 2 * half[:, 1]
    aux_w = np.stack([L, eave, styles[style, 4], 0 * L, wall_col[:, 0], wall_col[:, 1], wall_col[:, 2], bh], 1)[idx2]
    mb.add(
        Vf,
        gables,
        Mat.WALL,
        object_id=bids[idx2],
        style=style[idx2],
        origin=g_origin,
        axis_u=g_u,
        axis_v=(0, 0, 1),
        aux=aux_w,
    )


def _props(mb: MeshBuilder, g: RoadGraph, town: TownConfig, occ: Occupancy, fences: list, rng: np.random.Generator):
    """Lamps, trees (along streets and in parks), traffic signs and fences into ``mb``. Returns
    (lamp heads (n, 3), number of trees, parking slots (n, 4): x, y, heading, road half width)."""
    street = _street_props(g, town, rng)
    lamps_xyz = _lamps(mb, street.lamp_pos, street.lamp_dir, town)
    n_trees = _trees(mb, street.tree_pos, occ, town, rng)
    _signs(mb, street.sign_pos, street.sign_dir, town, rng)
    _fences(mb, fences, town, rng)
    slots_arr = np.concatenate(street.slots) if street.slots else np.zeros((0, 4))
    return lamps_xyz, n_trees, slots_arr


@dataclass
class _StreetProps:
    """Where the props along the roads go, per road in lists: lamp bases (n, 2) and the directions
    of their arms toward the road (n, 2), street trees (n, 2), signs (position and the direction
    their plate faces, (2,) each) and parking slots (n, 4): x, y, heading, road half width."""

    lamp_pos: list[np.ndarray] = field(default_factory=list)
    lamp_dir: list[np.ndarray] = field(default_factory=list)
    tree_pos: list[np.ndarray] = field(default_factory=list)
    sign_pos: list[np.ndarray] = field(default_factory=list)
    sign_dir: list[np.ndarray] = field(default_factory=list)
    slots: list[np.ndarray] = field(default_factory=list)


def _street_props(g: RoadGraph, town: TownConfig, rng: np.random.Generator) -> _StreetProps:
    """Along each road between its junctions' sidewalks: lamps on alternating sides, trees on both
    sidewalks (of avenues, and of 70 % of the other roads) away from the lamps, signs on the right
    before junctions of three or more roads, and parking bays on streets and avenues."""
    deg = g.degree()
    out = _StreetProps()
    for road in g.roads:
        L = road.length_m
        w = road.half_width_m
        q0 = g.sidewalk_radius_m[road.a] + 1.5
        q1 = L - g.sidewalk_radius_m[road.b] - 1.5
        if q1 <= q0:
            continue
        # lamps, alternating sides
        n_l = max(1, int((q1 - q0) // town.lamp_spacing_m))
        s_l = q0 + (np.arange(n_l) + 0.5) * (q1 - q0) / n_l
        side_l = np.where(np.arange(n_l) % 2 == 0, -1.0, 1.0) * (1 if road.id % 2 else -1)
        p, t = road.point_at(s_l)
        nl = np.stack([-t[:, 1], t[:, 0]], 1)
        base = p + nl * (side_l * (w + 0.4))[:, None]
        out.lamp_pos.append(base)
        out.lamp_dir.append(-nl * side_l[:, None])
        # trees on sidewalks (some streets have none)
        if road.kind == "avenue" or rng.random() < 0.7:
            for side in (-1.0, 1.0):
                n_t = int((q1 - q0) // town.tree_spacing_m)
                if n_t < 1:
                    continue
                s_t = q0 + (np.arange(n_t) + rng.uniform(0.3, 0.7, n_t)) * (q1 - q0) / n_t
                p, t = road.point_at(s_t)
                nl = np.stack([-t[:, 1], t[:, 0]], 1)
                pos = p + nl * side * (w + 1.1)
                far = np.min(np.linalg.norm(pos[:, None] - base[None], axis=2), axis=1) > 5.0
                out.tree_pos.append(pos[far])
        # signs at the approach to junctions, on the right
        for end, node in ((1, road.b), (0, road.a)):
            if deg[node] < 3 or rng.random() >= town.sign_probability:
                continue
            s = q1 - 1.0 if end == 1 else q0 + 1.0
            p, t = road.point_at(np.array([s]))
            heading = t[0] if end == 1 else -t[0]
            right = np.array([heading[1], -heading[0]])
            out.sign_pos.append(p[0] + right * (w + 0.6))
            out.sign_dir.append(-heading)
        # parking bays on streets and avenues
        if road.kind in ("street", "avenue"):
            s_p = np.arange(q0 + 4.0, q1 - 4.0, 6.0)
            if len(s_p):
                p, t = road.point_at(s_p)
                nl = np.stack([-t[:, 1], t[:, 0]], 1)
                for side in (-1.0, 1.0):
                    xy = p + nl * side * (w - town.parking_width_m / 2)
                    heading = np.arctan2(t[:, 1], t[:, 0]) + (0.0 if side < 0 else np.pi)
                    out.slots.append(np.c_[xy, heading, np.full(len(xy), w)])
    return out


def _lamps(mb: MeshBuilder, lamp_pos: list[np.ndarray], lamp_dir: list[np.ndarray], town: TownConfig) -> np.ndarray:
    """Street lamps (pole, arm toward the road, head) into ``mb``; returns their heads' light positions (n, 3)."""
    if not lamp_pos:
        return np.zeros((0, 3))
    base = np.concatenate(lamp_pos)
    d = np.concatenate(lamp_dir)
    n = len(base)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    h = 7.0
    add_boxes(
        mb,
        Boxes(np.c_[base, np.full(n, town.sidewalk_height_m)], np.full((n, 2), 0.09), np.full(n, h), yaw),
        Mat.POLE,
        faces=(0, 1, 2, 3),
    )
    arm_c = base + d * 0.8
    add_boxes(
        mb,
        Boxes(np.c_[arm_c, np.full(n, h - 0.12)], np.tile([0.85, 0.06], (n, 1)), np.full(n, 0.12), yaw),
        Mat.POLE,
    )
    head = base + d * 1.55
    add_boxes(
        mb, Boxes(np.c_[head, np.full(n, h - 0.3)], np.tile([0.35, 0.17], (n, 1)), np.full(n, 0.18), yaw), Mat.LAMP
    )
    return np.c_[head, np.full(n, h - 0.4)]


def _trees(
    mb: MeshBuilder, tree_pos: list[np.ndarray], occ: Occupancy, town: TownConfig, rng: np.random.Generator
) -> int:
    """The street trees at ``tree_pos`` and park trees on free land (clustered: candidates in the
    "park" cells of a coarse random field), each a trunk and one of a few canopy shapes, sized and
    turned at random, into ``mb``; returns their number."""
    canopies, CT, TV, TT = _tree_templates(rng)
    tp = np.concatenate(tree_pos) if tree_pos else np.zeros((0, 2))
    lo = np.array([occ.x0, occ.y0])
    area_ha = occ.nx * occ.ny * occ.res**2 / 1e4
    n_cand = int(area_ha * town.park_trees_per_ha * 3)
    if n_cand:
        cand = lo + rng.uniform(0, 1, (n_cand, 2)) * np.array([occ.nx, occ.ny]) * occ.res
        ok = occ.free_at(cand, radius=3.0)
        park = _value_noise_np(cand / 60.0, 7) > 0.55
        tp = np.concatenate([tp, cand[ok & park][: int(area_ha * town.park_trees_per_ha)]])
    n_trees = len(tp)
    if not n_trees:
        return 0
    trunk_h = rng.uniform(2.0, 3.5, n_trees)
    rx = rng.uniform(1.8, 3.2, n_trees)
    rz = rx * rng.uniform(1.0, 1.4, n_trees)
    yaw = rng.uniform(0, 2 * np.pi, n_trees)
    variant = rng.integers(len(canopies), size=n_trees)
    base_z = np.full(n_trees, town.sidewalk_height_m)
    base_z[occ.free_at(tp)] = GROUND_Z  # park trees stand on the ground
    tv, tt = instances(
        TV, TT, np.c_[tp, base_z], np.c_[np.full(n_trees, 0.22), np.full(n_trees, 0.22), trunk_h + rz * 0.5], yaw
    )
    tt = _outward(tv, tt, np.repeat(np.c_[tp, base_z + 1.0], len(TT), axis=0))
    mb.add(tv, tt, Mat.TRUNK, object_id=np.repeat(np.arange(n_trees), len(TT)))
    hashes = ((np.arange(n_trees) * 2654435761) % 1000003) / 1000003.0
    for k, CV in enumerate(canopies):
        sel = np.nonzero(variant == k)[0]
        if not len(sel):
            continue
        centre = np.c_[tp[sel], base_z[sel] + trunk_h[sel] + rz[sel] * 0.8]
        cv, ct = instances(CV, CT, centre, np.c_[rx[sel], rx[sel], rz[sel]], yaw[sel])
        ct = _outward(cv, ct, np.repeat(centre, len(CT), axis=0))
        mb.add(cv, ct, Mat.FOLIAGE, object_id=np.repeat(sel, len(CT)), aux=np.repeat(hashes[sel], len(CT))[:, None])
    return n_trees


def _signs(
    mb: MeshBuilder, sign_pos: list[np.ndarray], sign_dir: list[np.ndarray], town: TownConfig, rng: np.random.Generator
) -> None:
    """Traffic signs into ``mb``: a pole and a plate (of a random kind) facing oncoming traffic."""
    if not sign_pos:
        return
    sp = np.array(sign_pos)
    sd = np.array(sign_dir)
    n = len(sp)
    yaw = np.arctan2(sd[:, 1], sd[:, 0]) + np.pi / 2  # plate's local -y faces along sd
    add_boxes(
        mb,
        Boxes(np.c_[sp, np.full(n, town.sidewalk_height_m)], np.full((n, 2), 0.04), np.full(n, 2.2), yaw),
        Mat.POLE,
        faces=(0, 1, 2, 3),
    )
    kind = rng.integers(0, 4, n).astype(float)
    add_boxes(
        mb,
        Boxes(np.c_[sp, np.full(n, 2.0)], np.tile([0.35, 0.02], (n, 1)), np.full(n, 0.7), yaw),
        {3: Mat.SIGN, "default": Mat.POLE},
        aux=kind[:, None],
        style=kind.astype(int),
    )


def _fences(mb: MeshBuilder, fences: list, town: TownConfig, rng: np.random.Generator) -> None:
    """Fences along the lot gaps ``fences`` (road, side, s from, s to) into ``mb``: posts about
    2.5 m apart behind the sidewalk and a panel between each two, of a random kind per fence."""
    segs = []
    for road, side, s0, s1 in fences:
        ss = np.linspace(s0, s1, max(2, int((s1 - s0) / 2.5) + 1))
        p, t = road.point_at(ss)
        nl = np.stack([-t[:, 1], t[:, 0]], 1)
        q = p + nl * side * (road.half_width_m + town.sidewalk_width_m + 0.4)
        segs.append((q, float(rng.integers(0, 2))))
    if not segs:
        return
    posts = np.concatenate([q for q, _ in segs])
    add_boxes(
        mb,
        Boxes(
            np.c_[posts, np.full(len(posts), GROUND_Z)],
            np.full((len(posts), 2), 0.05),
            np.full(len(posts), 1.4),
            np.zeros(len(posts)),
        ),
        Mat.FENCE,
        aux=np.zeros((len(posts), 1)),
    )
    pc, ph, py, pk = [], [], [], []
    for q, fence_kind in segs:
        a, b = q[:-1], q[1:]
        d = b - a
        L = np.linalg.norm(d, axis=1)
        pc.append((a + b) / 2)
        ph.append(np.c_[L / 2, np.full(len(L), 0.02)])
        py.append(np.arctan2(d[:, 1], d[:, 0]))
        pk.append(np.full(len(L), fence_kind))
    n = sum(len(x) for x in pc)
    add_boxes(
        mb,
        Boxes(np.c_[np.concatenate(pc), np.full(n, 0.05)], np.concatenate(ph), np.full(n, 1.2), np.concatenate(py)),
        Mat.FENCE,
        aux=np.concatenate(pk)[:, None],
    )


def _ground_and_hills(mb: MeshBuilder, half: np.ndarray, margin: float, rng: np.random.Generator) -> None:
    r_h = float(np.hypot(*half)) + margin
    R = r_h + 80.0
    n = 8
    xs = np.linspace(-R, R, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    V = np.c_[X.ravel(), Y.ravel(), np.full(X.size, GROUND_Z)]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + j).ravel()
    tris = np.concatenate([np.stack([a, a + n + 1, a + n + 2], 1), np.stack([a, a + n + 2, a + 1], 1)])
    tris = _orient(V, tris, np.tile([0, 0, 1.0], (len(tris), 1)))
    mb.add(V, tris, Mat.GROUND, origin=(0, 0, GROUND_Z))
    # a ring of low hills as a horizon
    m = 180
    th = np.linspace(0, 2 * np.pi, m, endpoint=False)
    h = 18 + 10 * np.sin(3 * th + rng.uniform(0, 6)) + 8 * np.sin(7 * th + rng.uniform(0, 6)) + rng.uniform(0, 10, m)
    inner = np.c_[r_h * np.cos(th), r_h * np.sin(th), np.full(m, GROUND_Z)]
    outer = np.c_[(r_h + 70) * np.cos(th), (r_h + 70) * np.sin(th), h]
    V = np.concatenate([inner, outer])
    k = np.arange(m)
    tris = np.concatenate([np.stack([k, (k + 1) % m, m + (k + 1) % m], 1), np.stack([k, m + (k + 1) % m, m + k], 1)])
    tris = _orient(V, tris, -np.concatenate([inner[k], inner[k]]) * np.array([1, 1, 0]))
    mb.add(V, tris, Mat.HILL, origin=(0, 0, 0))


def _value_noise_np(xy: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1] on a unit lattice (float64; for placement, not rendering)."""
    i = np.floor(xy).astype(np.int64)
    f = xy - i
    f = f * f * (3 - 2 * f)

    def h(ix, iy):
        v = (ix * 374761393 + iy * 668265263 + seed * 1442695041) & 0xFFFFFFFF
        v = ((v ^ (v >> 13)) * 1274126177) & 0xFFFFFFFF
        return (v & 0xFFFF) / 65535.0

    a, b = h(i[:, 0], i[:, 1]), h(i[:, 0] + 1, i[:, 1])
    c, d = h(i[:, 0], i[:, 1] + 1), h(i[:, 0] + 1, i[:, 1] + 1)
    return (a * (1 - f[:, 0]) + b * f[:, 0]) * (1 - f[:, 1]) + (c * (1 - f[:, 0]) + d * f[:, 0]) * f[:, 1]


# --- parked cars (per session) --------------------------------------------------------------------

CAR_COLOURS = np.array(
    [
        (0.8, 0.8, 0.82),
        (0.05, 0.05, 0.06),
        (0.5, 0.52, 0.55),
        (0.6, 0.05, 0.04),
        (0.05, 0.15, 0.45),
        (0.9, 0.9, 0.88),
        (0.25, 0.3, 0.25),
        (0.7, 0.55, 0.1),
        (0.3, 0.32, 0.36),
        (0.55, 0.6, 0.7),
    ]
)


def parked_cars(town: Town, rng: np.random.Generator, occupancy: float | None = None) -> Geometry:
    """A session's parked cars: each parking slot taken with the town's occupancy probability."""
    slots = town.parking_slots
    p = town.config.town.parked_car_occupancy if occupancy is None else occupancy
    take = rng.random(len(slots)) < p
    sl = slots[take]
    n = len(sl)
    if n == 0:
        return _empty_geometry()
    length = rng.uniform(3.8, 4.8, n)
    width = rng.uniform(1.7, 1.9, n)
    yaw = sl[:, 2] + rng.normal(0, 0.03, n)
    fwd = np.c_[np.cos(yaw), np.sin(yaw)]
    left = np.c_[-fwd[:, 1], fwd[:, 0]]
    xy = sl[:, :2] + fwd * rng.uniform(-0.5, 0.5, n)[:, None] + left * rng.uniform(-0.15, 0.15, n)[:, None]
    colour = CAR_COLOURS[rng.integers(len(CAR_COLOURS), size=n)] * rng.uniform(0.85, 1.1, (n, 1))
    body_h = rng.uniform(0.65, 0.8, n)
    cab_len = length * rng.uniform(0.45, 0.55, n)
    cab_h = rng.uniform(0.45, 0.55, n)
    return car_meshes(CarShapes(length, width, body_h, cab_len, cab_h, colour), xy, yaw)


@dataclass
class CarShapes:
    """The sizes (m) and colours of ``n`` cars: a body box on wheels and a glass cab on it."""

    length: np.ndarray  # (n,)
    width: np.ndarray  # (n,)
    body_h: np.ndarray  # (n,) body height above its 0.3 m ground clearance
    cab_len: np.ndarray  # (n,)
    cab_h: np.ndarray  # (n,)
    colour: np.ndarray  # (n, 3) linear RGB

    def take(self, k: np.ndarray) -> CarShapes:
        return CarShapes(*(getattr(self, f)[k] for f in ("length", "width", "body_h", "cab_len", "cab_h", "colour")))


def car_meshes(shape: CarShapes, xy: np.ndarray, yaw: np.ndarray) -> Geometry:
    """Cars of ``shape`` standing on z = 0 at ``xy`` (n, 2) heading ``yaw`` (n,): body, cab, four wheels."""
    n = len(xy)
    mb = MeshBuilder()
    fwd = np.c_[np.cos(yaw), np.sin(yaw)]
    left = np.c_[-fwd[:, 1], fwd[:, 0]]
    length, width, colour = shape.length, shape.width, shape.colour
    ids = np.arange(n)
    add_boxes(
        mb,
        Boxes(np.c_[xy, np.full(n, 0.3)], np.c_[length / 2, width / 2], shape.body_h, yaw),
        Mat.CAR_BODY,
        object_id=ids,
        aux=colour,
    )
    cab = xy - fwd * (0.08 * length)[:, None]
    add_boxes(
        mb,
        Boxes(np.c_[cab, 0.3 + shape.body_h], np.c_[shape.cab_len / 2, width / 2 - 0.08], shape.cab_h, yaw),
        {4: Mat.CAR_BODY, "default": Mat.CAR_GLASS},
        object_id=ids,
        aux=colour,
    )
    wheels = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            wheels.append(xy + fwd * (sx * (length / 2 - 0.75))[:, None] + left * (sy * (width / 2 - 0.12))[:, None])
    wc = np.concatenate(wheels)
    nw = len(wc)
    add_boxes(
        mb,
        Boxes(np.c_[wc, np.zeros(nw)], np.tile([0.33, 0.12], (nw, 1)), np.full(nw, 0.62), np.tile(yaw, 4)),
        Mat.CAR_WHEEL,
    )
    return mb.build()


def _empty_geometry() -> Geometry:
    z = np.zeros
    return Geometry(
        z((0, 3)),
        z((0, 3), np.int32),
        z(0, np.uint8),
        z(0, np.int32),
        z(0, np.int16),
        z((0, 3), np.float32),
        z((0, 3), np.float32),
        z((0, 3), np.float32),
        z((0, 8), np.float32),
    )


# --- roads around an external path ----------------------------------------------------------------


def roads_around_path(town: TownConfig, path_xy: np.ndarray, rng: np.random.Generator) -> RoadGraph:
    """A procedural town over the path's extent, with the path as one road (the vehicle in its
    right-hand lane) and the procedural roads that would cross its corridor removed."""
    lo, hi = path_xy.min(axis=0), path_xy.max(axis=0)
    centre = (lo + hi) / 2
    size = np.maximum(hi - lo + 2 * town.block_m, 2 * town.block_m)
    proc = generate_roads(town.model_copy(update={"size_m": (float(size[0]), float(size[1]))}), rng)
    # shift the road to the left of the path so that the vehicle drives in the right-hand lane
    d = np.gradient(path_xy, axis=0)
    t = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    road_line = path_xy + np.stack([-t[:, 1], t[:, 0]], 1) * DRIVE_LANE_CENTER_M
    keep = _simplify(road_line, 0.05)
    road_line = road_line[keep]
    corridor = town.street_half_width_m * 2 + town.sidewalk_width_m * 2 + 2.0
    nodes = proc.nodes_xy + centre
    near = _dist_to_polyline(nodes, road_line) < corridor + 5
    roads = []
    for r in proc.roads:
        poly = r.polyline + centre
        if near[r.a] or near[r.b] or (_dist_to_polyline(_densify(poly, 5.0), road_line) < corridor).any():
            continue
        roads.append(Road(0, r.a, r.b, r.kind, r.half_width_m, poly))
    used = sorted({r.a for r in roads} | {r.b for r in roads})
    remap = {old: new for new, old in enumerate(used)}
    nodes_xy = [nodes[o] for o in used]
    out = [Road(k, remap[r.a], remap[r.b], r.kind, r.half_width_m, r.polyline) for k, r in enumerate(roads)]
    a = len(nodes_xy)
    nodes_xy += [road_line[0], road_line[-1]]
    out.append(Road(len(out), a, a + 1, "track", town.street_half_width_m, road_line))
    g = RoadGraph(np.array(nodes_xy), out)
    compute_junction_radii(g, town.sidewalk_width_m)
    return g


DRIVE_LANE_CENTER_M = 1.75  # mapkit choice: centre of a 3.5 m lane right of the centre line


def _densify(poly: np.ndarray, step: float) -> np.ndarray:
    S = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s = np.linspace(0, S[-1], max(2, int(S[-1] / step) + 1))
    return np.stack([np.interp(s, S, poly[:, 0]), np.interp(s, S, poly[:, 1])], 1)


def _dist_to_polyline(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    a, b = poly[:-1], poly[1:]
    d = b - a
    L2 = np.maximum((d * d).sum(1), 1e-12)
    out = np.full(len(p), np.inf)
    for k0 in range(0, len(a), 512):
        A, D, LL = a[k0 : k0 + 512], d[k0 : k0 + 512], L2[k0 : k0 + 512]
        t = np.clip(((p[:, None, :] - A[None]) * D[None]).sum(-1) / LL[None], 0, 1)
        q = A[None] + t[..., None] * D[None]
        out = np.minimum(out, np.linalg.norm(p[:, None, :] - q, axis=-1).min(axis=1))
    return out


def _simplify(poly: np.ndarray, tol: float) -> np.ndarray:
    """Indices of a Douglas-Peucker simplification (iterative), endpoints kept."""
    keep = np.zeros(len(poly), bool)
    keep[0] = keep[-1] = True
    stack = [(0, len(poly) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = poly[i], poly[j]
        d = b - a
        L = np.linalg.norm(d)
        seg = poly[i + 1 : j] - a
        dist = np.abs(seg[:, 0] * d[1] - seg[:, 1] * d[0]) / L if L > 1e-9 else np.linalg.norm(seg, axis=1)
        k = int(np.argmax(dist))
        if dist[k] > tol:
            keep[i + 1 + k] = True
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return np.nonzero(keep)[0]


# --- writing and reading --------------------------------------------------------------------------


def write_ply(path: Path, g: Geometry) -> Path:
    """Binary little-endian PLY: double vertices, faces with their material and object id."""
    hdr = (
        "ply\nformat binary_little_endian 1.0\ncomment mapkit synthetic town, world ENU frame, metres\n"
        f"comment materials: {' '.join(f'{m.value}={m.name.lower()}' for m in Mat)}\n"
        f"element vertex {len(g.vertices)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(g.triangles)}\nproperty list uchar int vertex_indices\nproperty uchar material\n"
        "property int object_id\nend_header\n"
    )
    dt = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("m", "u1"), ("o", "<i4")])
    f = np.empty(len(g.triangles), dt)
    f["n"] = 3
    f["v"] = g.triangles
    f["m"] = g.material
    f["o"] = g.object_id
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(hdr.encode())
        fh.write(np.ascontiguousarray(g.vertices, "<f8").tobytes())
        fh.write(f.tobytes())
    return Path(path)


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (V, 3), triangles (T, 3), material (T,), object_id (T,)) of a PLY from ``write_ply``."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    nv = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in header if h.startswith("element face")).split()[-1])
    V = np.frombuffer(data, "<f8", count=3 * nv, offset=end).reshape(nv, 3)
    dt = np.dtype([("n", "u1"), ("v", "<i4", (3,)), ("m", "u1"), ("o", "<i4")])
    F = np.frombuffer(data, dt, count=nf, offset=end + 24 * nv)
    return V.copy(), F["v"].astype(np.int32), F["m"].copy(), F["o"].copy()


def write_roads(path: Path, g: RoadGraph, anchor: dict) -> Path:
    d = g.to_json()
    d["anchor"] = anchor
    return atomic_write_text(path, to_json(d))


def read_roads(path: Path) -> RoadGraph:
    return RoadGraph.from_json(json.loads(Path(path).read_text()))
