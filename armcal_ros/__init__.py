"""
armcal_ros: online background calibration of the cameras around a robot arm.

The arm itself is the calibration target; its forward-kinematics positions enter a bundle
adjustment
as measurements under a spatially correlated prior (Thompson, Daniel and Murray, 2004).
Only ``armcal_ros.ros`` imports rclpy and ROS message classes; everything else is plain numpy.
"""

__version__ = '0.1.0'
