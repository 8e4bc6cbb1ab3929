"""One session (drive) at a time: odometry trajectory, GPS alignment, the semi-dense map and the
georeferenced image database; ``build`` runs them in order."""
