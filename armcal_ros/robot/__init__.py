"""ROS-free robot model: URDF chain, forward kinematics, kinematic error parameters."""
