"""
Plain helpers shared by the test modules (not test modules: pytest collects nothing here).

``board_scene``: the rendered ChArUco scene (camera, board, mount, bags, folders, parameters);
``params_files``: parameter files of the node; ``ros_nodes``: the node and the test's own rclpy
client on DDS (imports rclpy: only for tests that ran ``pytest.importorskip('rclpy')``);
``cameras``: a calibrated camera and workspace points for the message tests.  The fixtures built
on them are in ``test/conftest.py``.
"""
