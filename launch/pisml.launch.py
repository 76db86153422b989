"""Launch the pisml_ros graph on a real ROS 2 install: measurement -> identifier -> analyser.

    ros2 launch pisml_ros pisml.launch.py [params_file:=/path/to/pisml.yaml]
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("pisml_ros"), "config", "pisml.yaml")
    params = LaunchConfiguration("params_file")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="node parameters (YAML)"),
        *(Node(package="pisml_ros", executable=name, name=name, parameters=[params], output="screen")
          for name in ("measurement", "identifier", "analyser", "gap")),
    ])
