"""A static transform tree: look up ``parent_from_child`` between any two frames of a vehicle.

Pure numpy. Built from the static extrinsics of a log (``/tf_static``); lookups chain through
common ancestors in either direction.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from mapkit.core.errors import InputError
from mapkit.core.geometry import invert_pose
from mapkit.core.types import FrameTransform


class FrameTree:
    def __init__(self, transforms: list[FrameTransform] | None = None):
        self._edges: dict[str, dict[str, np.ndarray]] = {}
        for t in transforms or []:
            self.add(t.parent_frame, t.child_frame, t.parent_from_child)

    def add(self, parent: str, child: str, parent_from_child: np.ndarray) -> None:
        T = np.asarray(parent_from_child, np.float64)
        self._edges.setdefault(parent, {})[child] = T
        self._edges.setdefault(child, {})[parent] = invert_pose(T)

    @property
    def frames(self) -> set[str]:
        return set(self._edges)

    def lookup(self, target: str, source: str) -> np.ndarray:
        """``target_from_source``: maps points in ``source`` coordinates into ``target``."""
        if target == source:
            return np.eye(4)
        if target not in self._edges or source not in self._edges:
            missing = target if target not in self._edges else source
            raise InputError(
                None,
                f"no extrinsic calibration for frame {missing!r} (known frames: {sorted(self.frames)})",
                field="tf",
            )
        # breadth-first search from target; accumulate target_from_x along the way
        seen = {target: np.eye(4)}
        queue = deque([target])
        while queue:
            f = queue.popleft()
            for nxt, f_from_nxt in self._edges[f].items():
                if nxt not in seen:
                    seen[nxt] = seen[f] @ f_from_nxt
                    if nxt == source:
                        return seen[nxt]
                    queue.append(nxt)
        raise InputError(None, f"frames {target!r} and {source!r} are not connected by the extrinsics", field="tf")
