"""Test-wide setup: DDS on loopback and a private ROS domain, before anything imports rclpy."""
import os
import random

from pisml_ros.ros.dds_env import configure_loopback_dds

os.environ.pop("ROS_LOCALHOST_ONLY", None)
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
configure_loopback_dds()
# a domain of our own, so parallel test runs on one machine don't see each other
os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(100, 200)))
os.environ.setdefault("MPLBACKEND", "Agg")
