"""What leaves the workspace: verified index bundles and maps and trajectories in another CRS."""
