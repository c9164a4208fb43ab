"""ROS-free renderer of textured box worlds through a calibrated, distorted camera, with exact z-depth."""
