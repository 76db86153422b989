"""ROS 2 node layer: thin nodes over the core (the only place that imports rclpy)."""
