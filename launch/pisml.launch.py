"""Launch the pisml_ros graph on a real ROS 2 install: measurement -> identifier -> analyser (+ gap).

    ros2 launch pisml_ros pisml.launch.py [params_file:=/path/to/pisml.yaml] [method:=mod-sindy]
                                          [smallsignal_path:=/path/to/smallsignal_bag]

The identifier publishes /pisml/model stage by stage (backbone, hybrid, explicit) and serves
/identifier/identify; the analyser publishes /pisml/stability per operating point and
/pisml/root_locus. A relative smallsignal_path is looked up from the working directory
(then from a source checkout); pass smallsignal_path:='' to train without small-signal data.
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
    identifier_overrides = {"method": LaunchConfiguration("method"),
                            "smallsignal_path": LaunchConfiguration("smallsignal_path")}
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params, description="node parameters (YAML)"),
        DeclareLaunchArgument("method", default_value="pisml",
                              description="identification method: pisml | pisml-nojac | std-sindy | mod-sindy | node"),
        DeclareLaunchArgument("smallsignal_path", default_value="bags/smallsignal_40dB",
                              description="small-signal records (CSV or bag) for the identifier; '' = none"),
        *(Node(package="pisml_ros", executable=name, name=name, output="screen",
               parameters=[params, identifier_overrides] if name == "identifier" else [params])
          for name in ("measurement", "identifier", "analyser", "gap")),
    ])
