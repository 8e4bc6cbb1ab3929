"""Faults that bench/fault_campaign.py meets through the command line, held here at the library's level.

A map truncated after its stage recorded it is refused by ``mapkit index structure`` with one error naming the file
and the stage to re-run, as align and triplets refuse it; read as it is, it would give an index of the points that
are left (or fail deep in the descriptor, naming neither).
"""

from __future__ import annotations

import pytest
from test_index_structure import FAST, make_street_workspace

from mapkit.core.errors import InputError
from mapkit.core.runio import mark_done
from mapkit.places.index_structure import build_structure_index


def test_a_truncated_map_is_refused_by_index_structure_naming_it(tmp_path):
    """A points.ply cut to a third after align recorded it: one error naming the file and `mapkit align`, and no
    index written."""
    ws = tmp_path / "ws"
    make_street_workspace(ws)
    mark_done(ws / "align", "test", outputs=True, sessions=["a", "b"])
    ply = ws / "align" / "sessions" / "b" / "map" / "points.ply"
    data = ply.read_bytes()
    ply.write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError, match=r"has \d+ bytes where its stage wrote \d+: re-run mapkit align") as err:
        build_structure_index(ws, "nbld", sessions=["a", "b"], overrides=FAST)
    assert err.value.path == ply
    assert not (ws / "indexes").exists()
