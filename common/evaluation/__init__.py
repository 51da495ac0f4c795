"""Scoring a run against ground truth (filled in below)."""
