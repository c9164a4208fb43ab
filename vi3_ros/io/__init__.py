"""Bag side of the data path: ROS 1 bags written with rosbags, rosbag2 MCAP via rosbags' converter, one reader."""
