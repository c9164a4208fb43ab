"""EuRoC-format datasets (ROS-free): calibration, ASL folders, sequences and clips, synthetic generation."""
