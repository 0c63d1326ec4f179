"""Dataset converters: the formats the field uses -> a rosbag2 MCAP the mapper reads."""
