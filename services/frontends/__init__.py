"""What people and other tools see: the web console and the ROS 2 view (its bridge
and CDR/type-hash codec)."""
