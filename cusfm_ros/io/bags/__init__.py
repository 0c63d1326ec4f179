"""ROS bag reading and writing through rosbags (mcap, sqlite3, ROS 1)."""
