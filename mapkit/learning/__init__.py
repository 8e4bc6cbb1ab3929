"""Training the 3D-CNN patch descriptor on the triplet dataset (the ``learning`` extra)."""
