"""ROS message <-> numpy conversions; the only place that knows message layouts (never imports rclpy)."""
