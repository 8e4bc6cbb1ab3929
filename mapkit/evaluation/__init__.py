"""Every evaluation against truth: metrics, the synthetic town's truth, and one module per stage
evaluated."""
