"""Image retrieval: dense SIFT/RootSIFT, VLAD with PCA-whitening, the deployable VLAD index, and
the pose measurement made from its hits."""
