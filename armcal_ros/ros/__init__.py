"""The only place that imports rclpy and ROS message types: node, conversions, replay."""
