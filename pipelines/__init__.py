"""End-to-end recipes that chain mapkit's stages by passing the paths each stage returns."""
