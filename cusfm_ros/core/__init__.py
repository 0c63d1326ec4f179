"""Pure computation: geometry, cameras, features, retrieval, graphs, mapping; no file or
ROS I/O."""
