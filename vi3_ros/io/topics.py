"""EuRoC's topic names and frame ids (as in the Vicon-room bags), and the message types the reader knows."""

IMAGE_TOPIC = "/cam0/image_raw"
IMU_TOPIC = "/imu0"
GT_TOPIC = "/vicon/firefly_sbx/firefly_sbx"
CAM_FRAME = "cam0"
IMU_FRAME = "imu4"
WORLD_FRAME = "world"
GT_CHILD_FRAME = "firefly_sbx"

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)  # camera frames, raw or JPEG/PNG
IMU_TYPE = "sensor_msgs/msg/Imu"
GT_TYPE = "geometry_msgs/msg/TransformStamped"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_STATIC_TOPIC = "/tf_static"
TF_TYPE = "tf2_msgs/msg/TFMessage"
#: the image_transport parameter -> the image message types it accepts
IMAGE_TRANSPORTS = {"auto": IMAGE_TYPES, "raw": (IMAGE_TYPE,), "compressed": (COMPRESSED_IMAGE_TYPE,)}
