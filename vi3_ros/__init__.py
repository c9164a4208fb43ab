"""ROS 2 shells of VI3: the rclpy node (``node.py``, imported only where rclpy exists), bag replay and the CLI."""

import os

# numpy's OpenBLAS pool, read once when numpy loads (before any module of this package imports it): its idle
# workers spin after each call, and on a 2-core machine they took ~0.2 s of CPU per clip from the backbone (the
# pipeline's matrices are small). One thread unless the user sets it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
