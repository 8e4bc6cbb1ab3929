"""Stage 3 of a session, ``map/``: the semi-dense map (:func:`mapkit.mapping.semidense.build_semidense_map`)
of the mapping camera's posed frames, in the workspace's local ENU frame (the trajectory's own frame when
the session is not georeferenced), with a top view and the map's metrics."""

from __future__ import annotations

from pathlib import Path

from mapkit.core.errors import InputError
from mapkit.core.geodesy import LocalFrame
from mapkit.core.runio import write_json
from mapkit.core.workspace import SessionDirs
from mapkit.core.writers import writes_workspace
from mapkit.io.plots import map_top_view
from mapkit.mapping.semidense import SemiDenseConfig, build_semidense_map
from mapkit.mapping.stages.common import plot_axes
from mapkit.mapping.stages.frames import PosedFrames

#: the version of this stage's algorithm, bumped whenever its output for the same inputs changes (it reruns)
STAGE_VERSION = 1


@writes_workspace("dirs", within=True)
def write_map(
    dirs: SessionDirs,
    frames: PosedFrames,
    cfg: SemiDenseConfig,
    frame: LocalFrame | None,
    progress: bool = True,
) -> Path:
    """Map the decoded ``frames`` into ``dirs.map``: points and observations (their coordinates stated in
    ``frame``, the session's local frame or None), a top view over the frames' trajectory and the metrics;
    returns the folder."""
    out = dirs.map
    gray_frames = ((i, f.stamp_ns, f.gray(), T) for i, f, T in frames)
    smap = build_semidense_map(gray_frames, frames.camera.info.K, cfg, progress=progress)
    if len(smap.points_world) == 0:  # an empty map would pass for a finished one; open3d cannot even read it
        raise InputError(
            frames.log.path,
            f"session {dirs.name}: the semi-dense map has 0 points from {len(smap.keyframe_ids)} keyframes of camera "
            f"{frames.camera.name}: no frame gave depth (frames outside the trajectory's time span, images without "
            "texture, or undecodable: see the warnings above); set `map: false` to build the session without a map",
            field="map",
        )
    smap.save(out, frame=frame)
    map_top_view(
        out / "top_view.png",
        smap.points_world,
        frames.trajectory.world_from_base[:, :3, 3],
        f"{dirs.name}: semi-dense map, {len(smap.points_world)} points",
        axes=plot_axes(frame),
    )
    m = {"points": int(len(smap.points_world)), "crs": None if frame is None else frame.to_dict()}
    m.update(smap.stats())
    write_json(out / "metrics.json", m)
    return out
