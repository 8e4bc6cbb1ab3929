"""Structural place recognition: voxelised patches, NBLD/M2DP/3D-CNN descriptors, the structure
index with keypoint-to-frame voting, and the triplet dataset."""
