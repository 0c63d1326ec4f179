"""The names ``bench/compare.py`` and its children share (standard library only: the driver
imports it and must stay small, see compare.py)."""

SCENES = {"street": ("street", "stereo"), "indoor": ("indoor", "stereo4")}
"""Simulator inputs: name -> (scene, rig)."""
INPUTS = ("kitti", *SCENES)
OURS = {"ours_view_graph_sift": ("view_graph", "sift", "knn"),
        "ours_radius_sift": ("radius", "sift", "knn"),
        "ours_view_graph_aliked": ("view_graph", "aliked", "lightglue"),
        "ours_view_graph_xfeat": ("view_graph", "xfeat", "lighterglue"),
        "ours_view_graph_aliked_adaptive": ("view_graph", "aliked", "lightglue", "adaptive"),
        "ours_view_graph_xfeat_adaptive": ("view_graph", "xfeat", "lighterglue", "adaptive")}
"""Our variants: name -> (pair selection, extractor, matcher[, "adaptive": the matcher's early
exit and point pruning at the reference's 0.95 / 0.99])."""
COLMAP = ("colmap_incremental", "colmap_global", "colmap_incremental_priors",
          "colmap_global_rig")
SYSTEMS = (*OURS, *COLMAP)
