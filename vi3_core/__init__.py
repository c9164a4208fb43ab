"""ROS-free core of VI3: preintegration, GT-free inertial initialisation, backbones, metric anchoring."""

__version__ = "0.1.0"
