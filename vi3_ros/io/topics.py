"""EuRoC's topic names and frame ids (as in the Vicon-room bags)."""

IMAGE_TOPIC = "/cam0/image_raw"
IMU_TOPIC = "/imu0"
GT_TOPIC = "/vicon/firefly_sbx/firefly_sbx"
CAM_FRAME = "cam0"
IMU_FRAME = "imu4"
WORLD_FRAME = "world"
GT_CHILD_FRAME = "firefly_sbx"

IMAGE_TYPE = "sensor_msgs/msg/Image"
IMU_TYPE = "sensor_msgs/msg/Imu"
GT_TYPE = "geometry_msgs/msg/TransformStamped"
