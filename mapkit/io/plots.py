"""PNG pictures for people: trajectories over GPS fixes, map top views. matplotlib, Agg backend."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapkit.core.runio import atomic_path


def _figure(size=(8, 8)):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=size, dpi=110)
    return plt, fig, ax


def _frame_equal(ax, xy: np.ndarray, min_ratio: float = 0.4, pad: float = 0.05) -> None:
    """Equal axes around ``xy``, the short side padded to at least ``min_ratio`` of the long one,
    so a straight drive is not drawn as a hairline strip."""
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = np.maximum(hi - lo, 1e-3)
    long = span.max() * (1 + 2 * pad)
    half = np.maximum(span * (1 + 2 * pad), min_ratio * long) / 2
    c = (lo + hi) / 2
    ax.set_xlim(c[0] - half[0], c[0] + half[0])
    ax.set_ylim(c[1] - half[1], c[1] + half[1])
    ax.set_aspect("equal", adjustable="box")


def _save(plt, fig, path: Path) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight")
    plt.close(fig)
    return path


def trajectory_over_gps(
    path: Path,
    traj_enu: np.ndarray,
    gps_enu: np.ndarray,
    inliers: np.ndarray,
    title: str,
    truth_enu: np.ndarray | None = None,
) -> Path:
    """The GPS-aligned trajectory over the fixes it was fitted to (used and rejected): ENU metres."""
    plt, fig, ax = _figure()
    if truth_enu is not None:
        ax.plot(truth_enu[:, 0], truth_enu[:, 1], color="0.6", lw=3, label="ground truth")
    ax.plot(traj_enu[:, 0], traj_enu[:, 1], "b-", lw=1.2, label="trajectory (aligned)")
    ax.scatter(gps_enu[inliers, 0], gps_enu[inliers, 1], s=6, c="g", label=f"GPS used ({int(inliers.sum())})")
    if (~inliers).any():
        ax.scatter(
            gps_enu[~inliers, 0],
            gps_enu[~inliers, 1],
            s=18,
            c="r",
            marker="x",
            label=f"GPS rejected ({int((~inliers).sum())})",
        )
    _frame_equal(ax, np.vstack([traj_enu[:, :2], gps_enu[:, :2]]))
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=4, fontsize=8, frameon=False)
    ax.grid(True, alpha=0.3)
    return _save(plt, fig, path)


def map_top_view(
    path: Path,
    points: np.ndarray,
    traj_enu: np.ndarray | None,
    title: str,
    max_points: int = 300_000,
    axes: tuple[str, str] = ("east", "north"),
    units: str = "m",
) -> Path:
    """Map points seen from above, coloured by height, with the trajectory. ``axes`` names the
    horizontal axes (east/north once georeferenced) and ``units`` their unit ("m", or "arbitrary
    units" for a reconstruction that is not)."""
    plt, fig, ax = _figure((9, 9))
    if len(points) > max_points:
        points = points[np.random.default_rng(0).choice(len(points), max_points, replace=False)]
    if len(points):
        z = points[:, 2]
        lo, hi = np.percentile(z, [2, 98]) if len(z) > 10 else (z.min(), z.max() + 1e-6)
        sc = ax.scatter(points[:, 0], points[:, 1], s=0.2, c=np.clip(z, lo, hi), cmap="viridis", linewidths=0)
        fig.colorbar(sc, ax=ax, shrink=0.6, label=f"height [{units}]")
    if traj_enu is not None and len(traj_enu):
        ax.plot(traj_enu[:, 0], traj_enu[:, 1], "r-", lw=0.8, label="trajectory")
        ax.legend(loc="best", fontsize=8)
    extent = [
        a
        for a in (points[:, :2] if len(points) else None, None if traj_enu is None else traj_enu[:, :2])
        if a is not None and len(a)
    ]
    if extent:
        _frame_equal(ax, np.vstack(extent))
    ax.set_xlabel(f"{axes[0]} [{units}]")
    ax.set_ylabel(f"{axes[1]} [{units}]")
    ax.set_title(title)
    return _save(plt, fig, path)


def raster_top_view(
    path: Path,
    points: np.ndarray,
    traj_xy: np.ndarray | None,
    title: str,
    axes: tuple[str, str] = ("east", "north"),
    max_side_px: int = 1000,
    marked: np.ndarray | None = None,
    marked_label: str = "",
) -> Path:
    """Every map point seen from above as an image: each pixel the mean height of the points it holds (viridis,
    2nd to 98th percentile), white where none, the trajectory in red, a scale bar and the height range in the
    caption; pixels holding one of the ``marked`` points (N, 3) drawn magenta over them, named ``marked_label``.
    Drawn with Pillow, not matplotlib: a dense map of millions of points in a fraction of a second, where a scatter
    plot would take seconds for a sample of it. Metres; the image's up is ``axes[1]``."""
    from PIL import Image, ImageDraw, ImageFont

    xy = np.asarray(points, np.float64)[:, :2]
    z = np.asarray(points, np.float64)[:, 2]
    extent = [a for a in (xy, None if traj_xy is None else np.asarray(traj_xy)[:, :2]) if a is not None and len(a)]
    lo, hi = (np.vstack(extent).min(axis=0), np.vstack(extent).max(axis=0)) if extent else (np.zeros(2), np.ones(2))
    pad = 0.03 * max(float((hi - lo).max()), 1.0)
    lo, hi = lo - pad, hi + pad
    px_m = float((hi - lo).max()) / max_side_px
    w, h = (np.ceil((hi - lo) / px_m).astype(int) + 1).tolist()
    rgb = np.full((h, w, 3), 255, np.uint8)
    has_marked = marked is not None and len(marked) > 0
    zlo = zhi = 0.0
    if len(xy):
        col = np.clip(((xy[:, 0] - lo[0]) / px_m).astype(np.intp), 0, w - 1)
        row = np.clip(((hi[1] - xy[:, 1]) / px_m).astype(np.intp), 0, h - 1)
        flat = row * w + col
        count = np.bincount(flat, minlength=w * h)
        mean_z = np.bincount(flat, z, minlength=w * h) / np.maximum(count, 1)
        zlo, zhi = (float(v) for v in np.percentile(z, [2, 98]))
        lut = (_viridis() * 255).astype(np.uint8)
        level = np.clip((mean_z - zlo) / max(zhi - zlo, 1e-6) * 255, 0, 255).astype(np.intp)
        seen = count > 0
        rgb.reshape(-1, 3)[seen] = lut[level[seen]]
    if has_marked:
        m = np.asarray(marked, np.float64)
        mc = np.clip(((m[:, 0] - lo[0]) / px_m).astype(np.intp), 0, w - 1)
        mr = np.clip(((hi[1] - m[:, 1]) / px_m).astype(np.intp), 0, h - 1)
        rgb[mr, mc] = (230, 0, 200)
    img = Image.fromarray(rgb)
    draw = ImageDraw.Draw(img)
    if traj_xy is not None and len(traj_xy):
        t = np.asarray(traj_xy)[:, :2]
        draw.line([((x - lo[0]) / px_m, (hi[1] - y) / px_m) for x, y in t], fill=(220, 30, 30), width=2)
    bar_m = _round_length(0.2 * (w * px_m))
    bar_px = bar_m / px_m
    draw.rectangle([20, h - 24, 20 + bar_px, h - 18], fill=(0, 0, 0))
    font = ImageFont.load_default(size=14)
    draw.text((20, h - 44), f"{bar_m:g} m", fill=(0, 0, 0), font=font)
    caption = Image.new("RGB", (w, 72 if has_marked else 52), (255, 255, 255))
    cd = ImageDraw.Draw(caption)
    cd.text((8, 4), title, fill=(0, 0, 0), font=ImageFont.load_default(size=16))
    cd.text(
        (8, 28),
        f"up: {axes[1]}, right: {axes[0]}; colour: mean height {zlo:.1f} m (blue) to {zhi:.1f} m (yellow); red: "
        "trajectory",
        fill=(60, 60, 60),
        font=font,
    )
    if has_marked:
        cd.text((8, 48), f"magenta: {marked_label}", fill=(60, 60, 60), font=font)
    out = Image.new("RGB", (w, h + caption.height), (255, 255, 255))
    out.paste(caption, (0, 0))
    out.paste(img, (0, caption.height))
    path = Path(path)
    with atomic_path(path) as tmp:
        out.save(tmp, format="PNG")
    return path


def _viridis() -> np.ndarray:
    """matplotlib's viridis as a (256, 3) table of RGB in [0, 1] (the colormap module alone, not pyplot)."""
    from matplotlib import colormaps

    return np.asarray(colormaps["viridis"](np.linspace(0.0, 1.0, 256)))[:, :3]


def _round_length(m: float) -> float:
    """The largest of 1, 2, 5 times a power of ten not above ``m`` (a scale bar's length)."""
    e = 10.0 ** np.floor(np.log10(max(m, 1e-9)))
    return float(max(k * e for k in (1, 2, 5) if k * e <= m))


def align_pairs_map(path: Path, sessions, pairs, max_points: int = 200_000) -> Path:
    """Top view of the aligned sessions with every registered submap pair: accepted in green,
    rejected in red (the QA picture of ``mapkit align``)."""
    plt, fig, ax = _figure((10, 10))
    allxy = []
    rng = np.random.default_rng(0)
    per = max(1, max_points // max(1, len(sessions)))
    for s in sessions:
        pts = s.points if len(s.points) <= per else s.points[rng.choice(len(s.points), per, replace=False)]
        ax.scatter(pts[:, 0], pts[:, 1], s=0.1, c="0.75", linewidths=0)
        ax.plot(s.poses[:, 0, 3], s.poses[:, 1, 3], lw=0.8, label=s.name)
        allxy.append(s.poses[:, :2, 3])
    n_acc = n_rej = 0
    for r in pairs:
        c = np.asarray(r.centre)
        if r.accepted:
            n_acc += 1
            ax.plot(c[0], c[1], "o", ms=4, mfc="none", mec="g")
        else:
            n_rej += 1
            ax.plot(c[0], c[1], "x", ms=5, c="r")
    ax.plot([], [], "o", mfc="none", mec="g", label=f"accepted pairs ({n_acc})")
    ax.plot([], [], "x", c="r", label=f"rejected pairs ({n_rej})")
    if allxy:
        _frame_equal(ax, np.vstack(allxy))
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title("multi-session alignment: submap pairs")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=4, fontsize=7, frameon=False)
    return _save(plt, fig, path)


def align_histograms(path: Path, pairs, lambda_icp_m: float, min_fitness: float) -> Path:
    """ICP RMSE and fitness of every registered pair, with the acceptance thresholds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4), dpi=110)
    rmse = np.array([r.rmse_m for r in pairs], np.float64)
    fit = np.array([r.fitness for r in pairs], np.float64)
    acc = np.array([r.accepted for r in pairs], bool)
    for ax, v, thr, label in ((a1, rmse, lambda_icp_m, "RMSE after ICP [m]"), (a2, fit, min_fitness, "fitness")):
        ok = np.isfinite(v)
        bins = np.linspace(0, max(float(np.nanmax(v[ok])) if ok.any() else 1.0, thr * 1.5), 40)
        ax.hist(
            [v[ok & acc], v[ok & ~acc]],
            bins=bins,
            stacked=True,
            color=["tab:green", "tab:red"],
            label=["accepted", "rejected"],
        )
        ax.axvline(thr, color="k", ls="--", lw=1, label=f"threshold {thr:g}")
        ax.set_xlabel(label)
        ax.set_ylabel("pairs")
        ax.legend(fontsize=8)
    fig.suptitle(f"ICP between sessions' submaps: {int(acc.sum())} accepted, {int((~acc).sum())} rejected")
    return _save(plt, fig, path)


def triplet_examples(path: Path, dataset, n: int = 4, seed: int = 0) -> Path:
    """A few triplets side by side, each grid drawn as its occupancy seen from above (count of
    occupied voxels per column): anchor, positive (same place, other session), negative."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows: list[tuple[str, np.ndarray]] = []
    for split in ("train", "test"):
        t = dataset.triplets(split)
        if len(t):
            rows.extend(
                (split, r) for r in t[np.random.default_rng(seed).choice(len(t), min(n, len(t)), replace=False)]
            )
    rows = rows[:n]
    fig, axes = plt.subplots(len(rows), 3, figsize=(7.5, 2.6 * len(rows)), dpi=100, squeeze=False)
    names = dataset.manifest["sessions"]
    for r, (split, ids) in enumerate(rows):
        grids = dataset.grids(ids, "occupancy")
        for c, (label, g) in enumerate(zip(("anchor", "positive", "negative"), grids, strict=True)):
            ax = axes[r, c]
            ax.imshow(g.sum(axis=2).T, origin="lower", cmap="magma")
            sess = names[int(dataset.table["session"][ids[c]])]
            ax.set_title(f"{label} ({split})\n{sess}, patch {int(ids[c])}", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("triplets: occupancy seen from above (x to the first observer)", fontsize=9)
    return _save(plt, fig, path)


def localization_track(
    path: Path, truth_xyz: np.ndarray, retrieval_xyz: np.ndarray, filter_xyz: np.ndarray, title: str
) -> Path:
    """Estimated against true trajectory of one query sequence (MCVL's Fig. 5): retrieval alone
    as points, the particle filter as a line."""
    plt, fig, ax = _figure((8, 8))
    ax.plot(truth_xyz[:, 0], truth_xyz[:, 1], color="0.5", lw=3, label="ground truth")
    ax.scatter(retrieval_xyz[:, 0], retrieval_xyz[:, 1], s=8, c="tab:orange", label="retrieval alone (mean shift)")
    ax.plot(filter_xyz[:, 0], filter_xyz[:, 1], "b-", lw=1.2, label="MCVL particle filter")
    _frame_equal(ax, np.vstack([truth_xyz[:, :2], filter_xyz[np.isfinite(filter_xyz[:, 0]), :2]]))
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=3, fontsize=8, frameon=False)
    ax.grid(True, alpha=0.3)
    return _save(plt, fig, path)


def training_curve(path: Path, history: list[dict], title: str = "CNN descriptor training") -> Path:
    """Loss (train, and test when scored) and test triplet accuracy per epoch (``mapkit train``)."""
    plt, fig, ax = _figure((7, 4.2))
    ep = np.array([r["epoch"] for r in history])
    ax.plot(ep, [r["loss"] for r in history], "o-", color="C0", label="train loss")
    if any("test_loss" in r for r in history):
        ax.plot(ep, [r.get("test_loss", np.nan) for r in history], "s--", color="C1", label="test loss")
    hard = [r["epoch"] for r in history if r.get("hard_triplets")]
    for k, e in enumerate(hard):
        ax.axvline(e - 0.5, color="0.6", lw=0.8, ls=":", label="hard triplets swapped in" if k == 0 else None)
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("epoch")
    ax.set_ylabel("triplet loss, Eq. (1)")
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if any("test_accuracy" in r for r in history):
        ax2 = ax.twinx()
        ax2.plot(ep, [r.get("test_accuracy", np.nan) for r in history], "^-", color="C2", label="test triplet accuracy")
        ax2.set_ylabel("test accuracy (d(X1,X2) < d(X1,X3))")
        ax2.set_ylim(0, 1)
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    ax.legend(handles, labels, loc="center right", fontsize=8)
    ax.set_title(title, fontsize=10)
    return _save(plt, fig, path)


def reference_model_statistics(
    path: Path, points_per_image: np.ndarray, track_lengths: np.ndarray, reprojection_errors_px: np.ndarray
) -> Path:
    """A triangulated reference model at a glance: points seen per image (in image order), the
    track-length histogram and the reprojection-error histogram of every observation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2, a3) = plt.subplots(1, 3, figsize=(14, 4), dpi=110)
    a1.bar(np.arange(len(points_per_image)), points_per_image, width=1.0, color="tab:blue")
    a1.set_xlabel("image (model order)")
    a1.set_ylabel("triangulated points seen")
    lengths = np.asarray(track_lengths, np.int64)
    top = int(lengths.max()) if len(lengths) else 2
    a2.hist(lengths, bins=np.arange(1.5, top + 1.5), color="tab:green")
    a2.set_xlabel("track length (images per point)")
    a2.set_ylabel("points")
    err = np.asarray(reprojection_errors_px, np.float64)
    a3.hist(err, bins=np.linspace(0, max(float(err.max()) if len(err) else 1.0, 1e-3), 40), color="tab:orange")
    if len(err):
        a3.axvline(float(np.median(err)), color="k", ls="--", lw=1, label=f"median {np.median(err):.2f} px")
        a3.legend(fontsize=8)
    a3.set_xlabel("reprojection error [px]")
    a3.set_ylabel("observations")
    fig.suptitle(f"reference model: {len(lengths)} points in {len(points_per_image)} images")
    return _save(plt, fig, path)
