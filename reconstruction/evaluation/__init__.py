"""Scoring a reconstruction against ground truth: map errors and image scores, thresholds, the report folder."""
