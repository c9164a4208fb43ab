"""ROS 2 shells of VI3: the rclpy node (``node.py``, imported only where rclpy exists), bag replay and the CLI."""

import os

# numpy's OpenBLAS pool, read once when numpy loads (before any module of this package imports it): its idle
# workers spin after each call, and on a 2-core machine they took ~0.2 s of CPU per clip from the backbone (the
# pipeline's matrices are small). One thread unless the user sets it.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# torch's OpenMP pool, read once when torch loads: after each operator the pool's idle workers spin before they
# sleep, and while other processes hold the cores a spinning worker takes the time slice the busy one needs. On the
# 2-core machine with two busy processes beside it, a TTR step took 313-1324 ms with the default and 72-85 ms passive
# (docs/node.md, `vi3 bench ttr`). Passive unless the user sets it.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")
