"""All sessions in one frame: submaps, ICP registration, the pose graph and its smooth corrections
(``mapkit align``)."""
