"""Synthetic scenes, rigs and bags with exact ground truth (tests, demo, benchmarks)."""
