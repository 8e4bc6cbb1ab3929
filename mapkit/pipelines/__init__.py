"""Recipes that run the stages in order (the demo on the synthetic town)."""
