"""Configuration of the PointNetVLAD export (:mod:`mapkit.places.pointnetvlad`).

A module of its own so that :class:`mapkit.places.triplets.TripletConfig` can nest it without importing
:mod:`mapkit.places.pointnetvlad` (which builds on :mod:`mapkit.places.triplets`).
"""

from __future__ import annotations

from pydantic import Field, model_validator

from mapkit.core.config import MapkitConfig


class PointNetVladConfig(MapkitConfig):
    enabled: bool = Field(
        False,
        description="Also write the triplet dataset in PointNetVLAD's layout, into ``folder`` "
        "(``mapkit triplets --pointnetvlad``, or mapkit.places.pointnetvlad.export_triplets_pointnetvlad).",
    )
    # PointNetVLAD, generating_queries/generate_training_tuples_baseline.py: KDTree.query_radius with r=10 for the
    # positives and everything outside r=50 for the negatives (paper, section 5: "structurally similar" within 10 m,
    # "structurally dissimilar" beyond 50 m)
    positive_distance_m: float = Field(
        10.0,
        gt=0,
        description="Training positives of a query: patches of its split within this "
        "horizontal (UTM) distance (PointNetVLAD, generate_training_tuples_baseline.py: 10 m).",
    )
    negative_distance_m: float = Field(
        50.0, gt=0, description="Training negatives: patches of its split farther than this (same source: 50 m)."
    )
    # PointNetVLAD, generating_queries/generate_test_sets.py: database neighbours of a query within r=25
    # (paper, section 5.2: "a retrieved point cloud is a correct match if it lies within 25 m of the query")
    evaluation_distance_m: float = Field(
        25.0,
        gt=0,
        description="Evaluation: the true matches of a query in another run's database lie "
        "within this distance (PointNetVLAD, generate_test_sets.py: 25 m).",
    )
    points: int = Field(
        4096,
        ge=16,
        description="Points per cloud (PointNetVLAD's submaps hold 4096). A patch with more is drawn "
        "at random without replacement; one with fewer repeats random points of its own.",
    )
    # PointNetVLAD, submap_generation/generate_submaps.m: pcfitplane(..., 0.5) removes the road plane before
    # downsampling
    ground_distance_m: float | None = Field(
        0.5,
        gt=0,
        description="Ground removal: the points within this distance of the patch's "
        "dominant near-horizontal plane (RANSAC) are dropped, as PointNetVLAD removed the road "
        "(generate_submaps.m, pcfitplane with 0.5). None keeps them.",
    )
    ground_max_tilt_deg: float = Field(
        15.0, ge=0, le=90, description="A plane counts as ground when its normal is within this angle of vertical."
    )
    max_negatives: int | None = Field(
        4000,
        ge=1,
        description="Negatives listed per query, a random sample when there are more: "
        "PointNetVLAD lists all, but its trainer only ever takes 4000 of them at a time "
        "(train_pointnetvlad.py, sampled_neg), and all of them would make the pickle grow with "
        "the square of the patches. None lists all.",
    )
    evaluation_prefix: str = Field(
        "mapkit",
        description="Evaluation pickles are PREFIX_evaluation_database.pickle and "
        "PREFIX_evaluation_query.pickle (PointNetVLAD's evaluate.py reads oxford_...: set 'oxford' to "
        "use it unchanged).",
    )
    folder: str = Field("pointnetvlad", description="Output folder, inside the triplet dataset's.")

    @model_validator(mode="after")
    def _check(self) -> PointNetVladConfig:
        if self.negative_distance_m < self.positive_distance_m:
            raise ValueError(
                f"negative_distance_m ({self.negative_distance_m}) must not be below positive_distance_m "
                f"({self.positive_distance_m})"
            )
        return self
