"""ROS message <-> numpy conversions; the only place that knows message layouts (never imports rclpy).

Modules: ``types`` (message classes by type name for a rosbags typestore or rclpy: ``MessageTypes``,
``jazzy_types``), ``stamps`` (Time <-> ns / s, headers), ``image`` (Image, CompressedImage, depth), ``imu``,
``camera_info``, ``poses`` (PoseArray, PoseStamped, Path, Odometry, TFMessage), ``pointcloud`` (PointCloud2),
``diagnostics`` (DiagnosticArray), ``builders`` (every builder in one import), ``fields`` (strict field readers),
``errors``. Malformed input raises ``errors.MalformedMessage`` (a ``ValueError``) naming the field and values.
"""
