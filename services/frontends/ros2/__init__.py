"""`telerobot ros2`: the system as ROS 2 (rmw_zenoh) sees it, with no ROS installed here."""
