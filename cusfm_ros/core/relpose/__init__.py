"""Relative pose estimation between views (two-view, stereo)."""
