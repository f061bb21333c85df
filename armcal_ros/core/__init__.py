"""ROS-free maths: camera model, priors, adjustment, initialisation, triangulation."""
