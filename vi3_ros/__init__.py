"""ROS 2 shells of VI3: the rclpy node (``node.py``, imported only where rclpy exists), bag replay and the CLI."""
