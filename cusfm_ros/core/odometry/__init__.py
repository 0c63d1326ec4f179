"""Visual odometry: initial poses for recordings that carry no odometry."""
