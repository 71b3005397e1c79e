"""Scenes and effects: simulated experiments with ground truth."""
