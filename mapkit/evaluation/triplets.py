"""``mapkit eval triplets``: how well a triplet dataset's positives agree on the true surface."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mapkit.core.runio import write_json
from mapkit.core.workspace import Workspace
from mapkit.core.writers import writes_workspace
from mapkit.evaluation.truth import error_transforms, session_truth, ws_from_town
from mapkit.mapping.trajectory import Trajectory
from mapkit.places.triplets import SPLITS, TripletDataset


@writes_workspace("dataset", within=True)
def evaluate_triplets(dataset: str | Path, workspace: str | Path | Workspace, truth: str | Path) -> dict:
    """Fraction of positive pairs whose true offset is below 0.5 m (and its distribution).

    Member s of a place put, after its ICP transform T_s, the true point E_s^-1 T_s^-1 p at the
    patch centre p (E_s = T_est T_gt^-1 of the aligned session's pose nearest to p); the offset
    of a positive pair is the distance between the two true points.
    """
    ds = TripletDataset(dataset)
    ws, truth = Workspace(workspace), Path(truth)
    town_to_ws = ws_from_town(truth, ws.require_frame())
    names = ds.manifest["sessions"]
    err = {}
    for k, n in enumerate(names):
        st, gt = session_truth(truth, n)
        tr = Trajectory.load(ws.aligned(n).trajectory)
        pos, E = error_transforms(tr.stamps_ns, tr.world_from_base, st, town_to_ws @ gt)
        err[k] = (cKDTree(pos[:, :2]), np.linalg.inv(E))
    t = ds.table
    true_pt = np.zeros((len(t["patch_id"]), 3))
    for i in range(len(true_pt)):
        tree, Einv = err[int(t["session"][i])]
        p = t["enu"][i]
        q = np.linalg.inv(t["transform"][i]) @ np.r_[p, 1.0]
        e = Einv[tree.query(q[:2])[1]]
        true_pt[i] = (e @ q)[:3]
    offsets = []
    for split in SPLITS:
        triplets = ds.triplets(split)
        if len(triplets):
            offsets.append(np.linalg.norm(true_pt[triplets[:, 0]] - true_pt[triplets[:, 1]], axis=1))
    off = np.concatenate(offsets) if offsets else np.zeros(0)
    res = {
        "positive_pairs": int(len(off)),
        "fraction_below_0.5m": float((off < 0.5).mean()) if len(off) else None,
        "offset_median_m": float(np.median(off)) if len(off) else None,
        "offset_p90_m": float(np.percentile(off, 90)) if len(off) else None,
    }
    write_json(Path(dataset) / "eval_triplets.json", res)
    return res
