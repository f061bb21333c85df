"""Files: rosbag2 bags (rosbags), camera_info YAML, extrinsics YAML, reports."""
