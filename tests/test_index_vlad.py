"""The VLAD index bundle: build on a tiny synthetic workspace, load, query, round trips, growth, resuming;
and retrieval on the real KITTI clip."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_dsift import textured_image
from test_vlad import shifted_and_brighter

from mapkit.core.blas import openblas_kernels
from mapkit.core.errors import InputError, InputWarning
from mapkit.core.geodesy import LocalFrame
from mapkit.core.geometry import make_pose, yaw_rotation
from mapkit.core.runio import read_timings
from mapkit.evaluation.retrieval import self_retrieval_kitti
from mapkit.mapping.imagedb import write_images_csv
from mapkit.retrieval.dsift import DsiftConfig
from mapkit.retrieval.index_vlad import (
    DATABASE_COLUMNS,
    FORMAT_VERSION,
    VladIndex,
    VladIndexConfig,
    build_vlad_index,
    encode_images,
    read_database_csv,
)
from mapkit.retrieval.vlad import VladConfig

SMALL_VLAD = VladConfig(
    dsift=DsiftConfig(region_widths=[16, 24]),
    num_words=8,
    pca_dim=12,
    kmeans_max_descriptors=20_000,
    kmeans_iterations=10,
)
PLACES = 8
SPACING_M = 40.0  # places further apart than the 25 m of a retrieval hit
FRAME = LocalFrame(51.7534, -1.2586, 59.0)
# session -> (offset of its camera positions from the place (m), appearance change of its images)
SESSIONS = {
    "train-a": ((0.0, 0.0, 0.0), dict(dx=0, dy=0, gain=1.0, offset=0)),
    "train-b": ((1.0, 0.5, 0.0), dict(dx=1, dy=0, gain=0.95, offset=5)),
    "test-c": ((0.5, -0.5, 0.0), dict(dx=-1, dy=1, gain=1.1, offset=-5)),
    "extra-d": ((-0.5, 0.5, 0.0), dict(dx=0, dy=-1, gain=1.05, offset=3)),
}


def place_pose(place: int, offset=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Camera at (40 p, 0, 1.5) + offset, looking along +x: optical z forward, x right, y down."""
    R_world_from_cam = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float) @ np.eye(3)
    R = yaw_rotation(0.1 * place) @ R_world_from_cam
    return make_pose(R, np.array([SPACING_M * place, 0.0, 1.5]) + np.asarray(offset))


def place_image(place: int, change: dict) -> np.ndarray:
    return shifted_and_brighter(textured_image(place), **change) if change["gain"] != 1.0 else textured_image(place)


def write_session(ws: Path, name: str) -> None:
    offset, change = SESSIONS[name]
    folder = ws / "sessions" / name / "imagedb"
    (folder / "images" / "cam").mkdir(parents=True, exist_ok=True)
    rel = []
    for p in range(PLACES):
        rel.append(f"images/cam/{p:03d}.png")
        cv2.imwrite(str(folder / rel[-1]), place_image(p, change))
    poses = np.stack([place_pose(p, offset) for p in range(PLACES)])
    write_images_csv(
        folder / "images.csv",
        np.arange(1, PLACES + 1),
        1_000_000_000 * (np.arange(PLACES) + 1),
        ["cam"] * PLACES,
        rel,
        poses,
        FRAME,
    )


def make_workspace(root: Path, names=("train-a", "train-b", "test-c", "extra-d")) -> Path:
    ws = root / "ws"
    ws.mkdir(parents=True, exist_ok=True)
    (ws / "origin.json").write_text(json.dumps(FRAME.to_dict()))
    for n in names:
        write_session(ws, n)
    return ws


def small_config(**kw) -> VladIndexConfig:
    base = dict(vlad=SMALL_VLAD, database_sessions=["train-a", "train-b"], top_k=4)
    base.update(kw)
    return VladIndexConfig(**base)


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, Path]:
    ws = make_workspace(tmp_path_factory.mktemp("vlad"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # 16 training images, 12 dimensions: nothing is capped
        out = build_vlad_index(ws, config=small_config(), progress=False)
    return ws, out


def copy_bundle(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_build_load_query_returns_the_place_and_its_pose(built):
    ws, out = built
    assert out == ws / "indexes" / "vlad"
    idx = VladIndex.load(out)
    assert len(idx) == 2 * PLACES and idx.dim == 12
    db = read_database_csv(out / "database.csv")
    assert list(db) == DATABASE_COLUMNS
    assert list(db["session"][:PLACES]) == ["train-a"] * PLACES
    assert db["image"][0] == "sessions/train-a/imagedb/images/cam/000.png"  # relative to the workspace
    assert (ws / db["image"][0]).is_file()
    lat, lon, _ = FRAME.enu_to_geodetic(place_pose(3)[None, :3, 3])
    np.testing.assert_allclose([db["lat_deg"][3], db["lon_deg"][3]], [lat[0], lon[0]], atol=1e-8)
    assert db["utm_epsg"][3] == FRAME.utm_epsg

    offset, change = SESSIONS["test-c"]
    for place in (2, 5):
        query = place_image(place, change)  # a third appearance, not in the database
        hits = idx.query(query)
        assert len(hits) == 4
        assert set(hits.sessions[:2]) == {"train-a", "train-b"}
        np.testing.assert_allclose(hits.translations[:2, 0], SPACING_M * place, atol=1.5)
        # the pose of the first hit is that database image's pose, exactly as written
        np.testing.assert_allclose(hits.world_from_cam[0], place_pose(place, SESSIONS[hits.sessions[0]][0]), atol=1e-4)
        assert np.all(np.diff(hits.distances) >= 0)
        z = idx.measurement(query)
        assert z.cluster_size == 2  # the two database images of the place, 1.1 m apart (< 5 m)
        np.testing.assert_allclose(z.translation, [SPACING_M * place + 0.5, 0.25, 1.5], atol=1e-3)
        assert np.degrees(np.arccos(np.clip((np.trace(z.rotation.T @ place_pose(place)[:3, :3]) - 1) / 2, -1, 1))) < 0.1
        # a vector query gives the same answer as the image
        v = idx.encode(query)
        np.testing.assert_array_equal(idx.query(v).ids, hits.ids)


def test_manifest_records_sessions_frame_and_every_file(built):
    ws, out = built
    m = json.loads((out / "manifest.json").read_text())
    assert m["format_version"] == FORMAT_VERSION
    assert m["database_sessions"] == ["train-a", "train-b"] and m["train_sessions"] == ["train-a", "train-b"]
    assert m["sessions"]["train-a"] | {"images_csv_sha256": None} == {
        "images": PLACES,
        "training_images": PLACES,
        "database": True,
        "training": True,
        "pose_source": "imagedb",
        "images_csv": "sessions/train-a/imagedb/images.csv",
        "images_csv_sha256": None,
    }
    assert "test-c" not in m["sessions"]
    assert m["frame"]["utm_crs_epsg"] == FRAME.utm_epsg
    assert m["index"] == {"kind": "flat", "faiss": "IndexFlatL2", "dim": 12, "metric": "squared L2", "ntotal": 16}
    # the kernel numpy's OpenBLAS ran (mapkit names it on import): the vocabulary's last bits depend on it
    assert "numpy" in m["openblas"] and m["openblas"] == openblas_kernels()
    listed = set(m["files"])
    on_disk = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()} - {"manifest.json", "timings.json"}
    assert listed == on_disk  # every file but the manifest and the run record (timings.json) is checksummed
    assert {"index.faiss", "database.csv", "config.yaml", "metrics.json", "encoder/vlad_encoder.npz"} <= listed
    assert "vectors.npy" not in listed  # a flat index holds the exact vectors itself
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["images_encoded"] == 16 and metrics["database_images_reused_from_training"] == 16
    assert read_timings(out)["images_encoded_per_s"] > 0 and "images_encoded_per_s" not in metrics
    # what the PCA-whitening learned on: 16 images of the two database sessions, 12 of 15 possible dimensions
    pca = {
        "dim": 12,
        "training_vectors": 16,
        "whitening": "power",
        "power": 0.5,
        "shrinkage": 0.0,
        "dim_requested": 12,
        "rank_limited": False,
        "training_sessions": {"train-a": PLACES, "train-b": PLACES},
        "training_vectors_in_database": 16,
        "training_vectors_from_training_frames": 0,
    }
    assert m["vlad"]["pca"] == pca and metrics["pca"] == pca


def test_training_uses_only_training_sessions(tmp_path, built):
    ws, _ = built
    # the PCA sees 8 images: 12 dimensions capped at 7, said once at build time
    with pytest.warns(InputWarning, match="capped from 12 to 7") as caught:
        out = build_vlad_index(ws, tmp_path / "b", small_config(train_sessions=["train-a"]), progress=False)
    assert len([w for w in caught if "capped" in str(w.message)]) == 1
    m = json.loads((out / "manifest.json").read_text())
    assert m["sessions"]["train-b"]["training"] is False and m["sessions"]["train-b"]["training_images"] == 0
    assert m["vlad"]["training_images"] == PLACES
    assert m["vlad"]["pca"]["training_sessions"] == {"train-a": PLACES} and m["vlad"]["pca"]["rank_limited"] is True
    assert m["vlad"]["pca"]["training_vectors_in_database"] == PLACES
    assert VladIndex.load(out).dim == PLACES - 1


def pairwise_sq(v: np.ndarray) -> np.ndarray:
    sq = ((v[:, None].astype(np.float64) - v[None]) ** 2).sum(-1)
    np.fill_diagonal(sq, np.inf)
    return sq


def test_database_learned_on_is_not_equidistant_and_finds_its_other_visit(tmp_path, built):
    """A PCA learned on n database images keeps n - 1 dimensions; fully whitened, those
    images are all at squared distance 2n / (n - 1) from each other (a database image searched
    against the others returns ties). The default, power-law whitening keeps their structure."""
    ws, _ = built
    cfg = small_config(train_sessions=["train-a"], vlad=SMALL_VLAD.model_copy(update={"pca_dim": 64}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # 64 dimensions capped at 7
        full = VladIndex.load(
            build_vlad_index(
                ws,
                tmp_path / "full",
                cfg.model_copy(update={"vlad": cfg.vlad.model_copy(update={"whitening": "full"})}),
                progress=False,
            )
        )
        default = VladIndex.load(build_vlad_index(ws, tmp_path / "power", cfg, progress=False))
    assert (
        full.manifest["vlad"]["pca"]["whitening"] == "full" and default.manifest["vlad"]["pca"]["whitening"] == "power"
    )
    learned_on = slice(0, PLACES)  # train-a: the PCA's 8 training images, rows 0..7 of the database
    sq_full = pairwise_sq(full.vectors()[learned_on])
    np.testing.assert_allclose(sq_full[np.isfinite(sq_full)], 2 * PLACES / (PLACES - 1), rtol=1e-4)
    sq = pairwise_sq(default.vectors()[learned_on])
    finite = sq[np.isfinite(sq)]
    assert finite.std() / finite.mean() > 0.05
    # every database image searched against the others: its nearest is the same place's other visit
    v = default.vectors()
    dist, ids = default.search(v, k=2)
    np.testing.assert_array_equal(ids[:, 0], np.arange(2 * PLACES))  # itself first
    np.testing.assert_array_equal(ids[:, 1] % PLACES, np.arange(2 * PLACES) % PLACES)
    np.testing.assert_array_equal(ids[:, 1] // PLACES, 1 - np.arange(2 * PLACES) // PLACES)


def test_corrupt_file_and_unknown_version_are_named(tmp_path, built):
    _, out = built
    b = copy_bundle(out, tmp_path / "b1")
    VladIndex.load(b)  # intact copy loads
    with open(b / "database.csv", "a") as f:
        f.write("\n")
    with pytest.raises(InputError) as e:
        VladIndex.load(b)
    assert e.value.path == b / "database.csv" and e.value.field == "sha256"

    b = copy_bundle(out, tmp_path / "b2")
    m = json.loads((b / "manifest.json").read_text())
    m["format_version"] = 99
    (b / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(InputError) as e:
        VladIndex.load(b)
    assert e.value.path == b / "manifest.json" and e.value.field == "format_version"
    assert "99" in str(e.value)

    b = copy_bundle(out, tmp_path / "b3")
    (b / "encoder" / "vlad_encoder.npz").unlink()
    with pytest.raises(InputError) as e:
        VladIndex.load(b)
    assert e.value.path == b / "encoder" / "vlad_encoder.npz"


def test_add_session_appends_without_relearning(tmp_path, built):
    ws, out = built
    b = copy_bundle(out, tmp_path / "grow")
    idx = VladIndex.load(b)
    vocab_before = (b / "encoder" / "vlad_encoder.npz").read_bytes()
    idx.add_session(ws, "extra-d")
    assert len(idx) == 3 * PLACES
    again = VladIndex.load(b)  # written to disk, checksums updated
    assert len(again) == 3 * PLACES and again.database_sessions == ["train-a", "train-b", "extra-d"]
    assert (b / "encoder" / "vlad_encoder.npz").read_bytes() == vocab_before
    assert list(again.database["entry_id"]) == list(range(3 * PLACES))
    # the new images are retrievable at their own poses
    hits = again.query(place_image(6, SESSIONS["test-c"][1]), k=3)
    assert set(hits.sessions) == {"train-a", "train-b", "extra-d"}
    np.testing.assert_allclose(hits.translations[:, 0], SPACING_M * 6, atol=1.5)
    # the added vectors are what the encoder gives for those files
    rows = again.database["session"] == "extra-d"
    paths = [ws / p for p in again.database["image"][rows]]
    np.testing.assert_allclose(again.vectors()[rows], encode_images(again.encoder, paths), atol=1e-6)
    with pytest.raises(InputError, match="already in the index") as e:
        again.add_session(ws, "extra-d")
    assert e.value.field == "sessions"
    with pytest.raises(InputError):
        again.add_session(ws, "train-a")
    assert len(VladIndex.load(b)) == 3 * PLACES
    assert not list(tmp_path.glob(".grow.*"))  # no partial folder left behind


def test_rerun_skips_and_interrupted_build_is_not_finished(tmp_path, built):
    ws, _ = built
    cfg = small_config(top_k=3)
    out = tmp_path / "idx"
    # an interrupted build: a partial folder of a process that is gone, holding a plausible manifest
    stale = tmp_path / ".idx.partial-999999999-deadbeef"
    stale.mkdir()
    (stale / "manifest.json").write_text(json.dumps({"format_version": FORMAT_VERSION}))
    build_vlad_index(ws, out, cfg, progress=False)
    assert not stale.exists()  # cleared by the next build
    VladIndex.load(out)
    t_manifest = (out / "manifest.json").stat().st_mtime_ns
    t_index = (out / "index.faiss").stat().st_mtime_ns
    assert build_vlad_index(ws, out, cfg, progress=False) == out
    assert (out / "manifest.json").stat().st_mtime_ns == t_manifest and (
        out / "index.faiss"
    ).stat().st_mtime_ns == t_index
    # a bundle that lost a file is not finished: the build runs again
    (out / "index.faiss").unlink()
    build_vlad_index(ws, out, cfg, progress=False)
    assert len(VladIndex.load(out)) == 2 * PLACES
    # a query-time setting is rewritten without encoding again; another encoder setting rebuilds
    t_index = (out / "index.faiss").stat().st_mtime_ns
    build_vlad_index(ws, out, cfg, overrides={"top_k": 5, "workers": 2}, progress=False)
    assert VladIndex.load(out).cfg.top_k == 5 and (out / "index.faiss").stat().st_mtime_ns == t_index
    build_vlad_index(ws, out, cfg, overrides={"vlad": {"num_words": 6}}, progress=False)
    assert (
        VladIndex.load(out).encoder.vocabulary.shape == (6, 128) and (out / "index.faiss").stat().st_mtime_ns != t_index
    )
    # a folder that is not a bundle is never replaced
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="not a VLAD index bundle"):
        build_vlad_index(ws, other, cfg, progress=False)
    assert (other / "notes.txt").read_text() == "keep me"


def test_ivf_bundle_keeps_vectors_and_answers_like_flat(tmp_path, built):
    ws, out = built
    flat = VladIndex.load(out)
    with pytest.warns(Warning, match="nlist capped"):
        b = build_vlad_index(ws, tmp_path / "ivf", small_config(index="ivf", ivf={"nlist": 4}), progress=False)
    ivf = VladIndex.load(b)
    m = ivf.manifest["index"]
    assert m["faiss"] == "IndexIVFFlat" and m["nlist"] == 1 and (b / "vectors.npy").is_file()
    np.testing.assert_array_equal(ivf.vectors(), flat.vectors())  # same training, same encoding
    q = flat.encode(place_image(4, SESSIONS["test-c"][1]))
    np.testing.assert_array_equal(ivf.query(q).ids, flat.query(q).ids)


def test_unknown_sessions_are_input_errors(tmp_path, built):
    ws, _ = built
    with pytest.raises(InputError) as e:
        build_vlad_index(ws, tmp_path / "x", small_config(database_sessions=["train-a", "nope"]), progress=False)
    assert e.value.field == "database_sessions" and "nope" in str(e.value)


def test_parallel_encoding_equals_serial(tmp_path, built):
    ws, out = built
    idx = VladIndex.load(out)
    paths = [ws / p for p in idx.database["image"][:4]]
    serial = encode_images(idx.encoder, paths, workers=1)
    parallel = encode_images(idx.encoder, paths, workers=2)
    np.testing.assert_array_equal(parallel, serial)  # same code, one thread each, rows in input order
    np.testing.assert_allclose(serial, idx.vectors()[:4], atol=1e-6)


def test_encodings_cache_encodes_each_file_once_and_notices_a_changed_file(tmp_path, built, monkeypatch):
    import mapkit.retrieval.vlad_index as iv  # encode_files calls encode_images there

    ws, out = built
    idx = VladIndex.load(out)
    src = [ws / p for p in idx.database["image"][:4]]
    paths = [shutil.copy(p, tmp_path / f"{i}{p.suffix}") for i, p in enumerate(src)]
    plain = idx.encode_files(paths[:3])
    encoded = []
    real = iv.encode_images
    monkeypatch.setattr(
        iv, "encode_images", lambda enc, ps, *a, **k: (encoded.append(len(ps)), real(enc, ps, *a, **k))[1]
    )
    first = idx.encode_files(paths[:3], cache_dir=tmp_path / "c")
    np.testing.assert_array_equal(first, plain)
    both = idx.encode_files(paths, cache_dir=tmp_path / "c")  # only the fourth is new
    assert encoded == [3, 1]
    np.testing.assert_array_equal(both[:3], plain)
    shutil.copy(src[0], paths[1])  # file 1 now holds image 0: a new size/mtime, encoded again
    again = idx.encode_files(paths[:2], cache_dir=tmp_path / "c")
    assert encoded == [3, 1, 1]
    np.testing.assert_allclose(again[1], again[0], atol=1e-6)


def test_real_kitti_clip_neighbours_are_adjacent_frames(kitti_clip):
    # the default power-law whitening, learned on the same 51 frames it ranks (measured here: median
    # gap 3 frames, 92% within 10; full whitening, which flattens their distances: 17 and 29%)
    cfg = VladConfig(
        dsift=DsiftConfig(half_resolution=True),
        num_words=16,
        pca_dim=16,
        kmeans_max_descriptors=30_000,
        kmeans_iterations=10,
    )
    assert cfg.whiten and cfg.whitening == "power"
    res = self_retrieval_kitti(kitti_clip, config=cfg, exclude=2)
    gaps = np.asarray(res["gaps"])
    assert res["frames"] == 51 and len(gaps) == 51
    assert gaps.min() >= 3  # itself and +-2 excluded
    assert np.median(gaps) <= 5, res["histogram"]
    assert np.mean(gaps <= 10) >= 0.8, res["histogram"]
    assert res["median_distance_m"] < 8.0


def add_training_frames(ws: Path, session: str, source: str) -> int:
    """Give ``session``'s image database training frames (``imagedb.training_frames``): the places
    as ``source`` sees them, images that are not in any database."""
    _, change = SESSIONS[source]
    folder = ws / "sessions" / session / "imagedb"
    (folder / "training" / "cam").mkdir(parents=True, exist_ok=True)
    rel = [f"training/cam/{p:03d}.png" for p in range(PLACES)]
    for p, r in enumerate(rel):
        cv2.imwrite(str(folder / r), place_image(p, change))
    poses = np.stack([place_pose(p, SESSIONS[source][0]) for p in range(PLACES)])
    write_images_csv(
        folder / "training.csv",
        np.arange(1, PLACES + 1),
        500_000_000 + 1_000_000_000 * np.arange(PLACES),
        ["cam"] * PLACES,
        rel,
        poses,
        FRAME,
    )
    return PLACES


def test_training_frames_give_the_pca_more_than_the_database(tmp_path, built):
    """The PCA learns also on the frames the build kept beside the database. Asked for 12
    dimensions, learned on the 8 database images alone, full whitening has 7 and makes them
    equidistant; with 8 training frames of the same places it has more vectors than dimensions (all
    12, not rank-limited), the database keeps its structure, and queries of a third appearance
    still find their place."""
    ws = Path(shutil.copytree(built[0], tmp_path / "ws"))
    shutil.rmtree(ws / "indexes")
    add_training_frames(ws, "train-a", "extra-d")
    vlad = SMALL_VLAD.model_copy(update={"whitening": "full"})
    cfg = small_config(database_sessions=["train-a"], train_sessions=["train-a"], vlad=vlad, training_frames=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # 12 dimensions capped at 7 without the frames
        without = VladIndex.load(
            build_vlad_index(
                ws, tmp_path / "db-only", cfg.model_copy(update={"training_frames": False}), progress=False
            )
        )
        with_frames = VladIndex.load(build_vlad_index(ws, tmp_path / "frames", cfg, progress=False))
    pca0, pca1 = without.manifest["vlad"]["pca"], with_frames.manifest["vlad"]["pca"]
    assert (pca0["dim"], pca0["training_vectors"], pca0["training_vectors_from_training_frames"]) == (
        PLACES - 1,
        PLACES,
        0,
    )
    assert (pca1["dim"], pca1["training_vectors"], pca1["training_vectors_from_training_frames"]) == (
        12,
        2 * PLACES,
        PLACES,
    )
    assert pca0["rank_limited"] is True and pca1["rank_limited"] is False
    assert pca1["training_vectors_in_database"] == PLACES and len(with_frames) == PLACES  # the frames are not indexed
    np.testing.assert_allclose(
        pairwise_sq(without.vectors())[~np.eye(PLACES, dtype=bool)], 2 * PLACES / (PLACES - 1), rtol=1e-4
    )
    sq = pairwise_sq(with_frames.vectors())[~np.eye(PLACES, dtype=bool)]
    assert sq.std() / sq.mean() > 0.05
    _, change = SESSIONS["test-c"]
    for place in range(PLACES):
        assert with_frames.query(place_image(place, change)).ids[0] == place


def test_another_whitening_from_a_bundle_equals_encoding_again(tmp_path, built, monkeypatch):
    """``reuse``: the full-whitening bundle re-scaled from the power-law one holds the vectors that
    encoding every image again with full whitening gives, without encoding a single image."""
    ws, out = built
    full_cfg = small_config(vlad=SMALL_VLAD.model_copy(update={"whitening": "full"}))
    encoded = VladIndex.load(build_vlad_index(ws, tmp_path / "encoded", full_cfg, progress=False))
    import mapkit.retrieval.vlad_build as vb

    def no_encoding(*a, **k):
        raise AssertionError("an image was encoded")

    monkeypatch.setattr(vb, "_learn_encoder", no_encoding)
    monkeypatch.setattr(vb, "_encode_database", no_encoding)
    derived = VladIndex.load(build_vlad_index(ws, tmp_path / "derived", full_cfg, progress=False, reuse=out))
    assert (
        derived.manifest["vlad"]["pca"]["whitening"] == "full"
        and derived.manifest["build_hash"] == encoded.manifest["build_hash"]
    )
    np.testing.assert_allclose(derived.vectors(), encoded.vectors(), atol=2e-5)
    q = place_image(4, SESSIONS["test-c"][1])
    np.testing.assert_allclose(derived.encode(q), encoded.encode(q), atol=2e-5)
    np.testing.assert_array_equal(derived.query(derived.encode(q)).ids, encoded.query(encoded.encode(q)).ids)
    assert json.loads((tmp_path / "derived" / "metrics.json").read_text())["rewhitened_from"] == str(out)
    # plain PCA (no whitening) from the full one, back again
    plain = build_vlad_index(
        ws,
        tmp_path / "plain",
        small_config(vlad=SMALL_VLAD.model_copy(update={"whiten": False})),
        progress=False,
        reuse=tmp_path / "derived",
    )
    assert VladIndex.load(plain).manifest["vlad"]["pca"]["whitening"] == "none"
    # a bundle of other images or settings is refused, naming it
    with pytest.raises(InputError, match="only the whitening"):
        build_vlad_index(
            ws,
            tmp_path / "other",
            small_config(vlad=SMALL_VLAD.model_copy(update={"whitening": "full", "num_words": 4})),
            progress=False,
            reuse=out,
        )
