"""ROS-free front end: marker detection, time pairing, sample store."""
