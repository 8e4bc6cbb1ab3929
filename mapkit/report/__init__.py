"""The HTML report that gathers a run's tables and pictures."""
