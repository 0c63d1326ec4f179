"""ROS 2 adapters. The only package that imports rclpy, and only lazily inside functions."""
