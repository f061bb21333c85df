"""Fields of ROS messages read by duck typing: rosbags' dataclasses and rclpy's messages alike."""


def stamp_ns(header_stamp):
    """Return a builtin_interfaces/Time as integer nanoseconds."""
    return int(header_stamp.sec) * 1_000_000_000 + int(header_stamp.nanosec)


def pose_from_msg(msg):
    """Return (translation (3,), quaternion xyzw (4,)) of a PoseStamped or TransformStamped."""
    if hasattr(msg, 'pose'):
        p, o = msg.pose.position, msg.pose.orientation
    elif hasattr(msg, 'transform'):
        p, o = msg.transform.translation, msg.transform.rotation
    else:
        raise ValueError(f'{type(msg).__name__} is neither a PoseStamped nor a '
                         'TransformStamped')
    return (p.x, p.y, p.z), (o.x, o.y, o.z, o.w)
