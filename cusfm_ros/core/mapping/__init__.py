"""Mapping: feature tracks, triangulation (bundle adjustment to follow)."""
