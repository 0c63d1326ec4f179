"""cusfm_ros: offline visual mapping, extrinsic refinement and localization from ROS 2 bags.

Layers, imports flowing one way: ``core`` -> ``io`` -> ``pipeline`` -> ``cli`` / ``ros``.
"""

__version__ = "0.1.0"
