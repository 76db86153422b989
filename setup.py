"""ament_python package pisml_ros; also a plain pip package with console scripts."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "pisml_ros"
NODES = ("measurement", "identifier", "analyser", "gap")

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="pisml_ros maintainers",
    maintainer_email="maintainers@pisml-ros.invalid",
    description="PISML identification of black-box grid-connected inverters for ROS 2",
    license="Apache-2.0",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "pisml = pisml_ros.cli:main",
            # ros2 run names (ament_python puts these in lib/pisml_ros) ...
            *(f"{node} = pisml_ros.ros.{node}:main" for node in NODES),
            # ... and the same nodes under unambiguous names for pip users
            *(f"pisml-{node} = pisml_ros.ros.{node}:main" for node in NODES),
        ],
    },
)
