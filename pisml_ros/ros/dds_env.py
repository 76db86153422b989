"""Keep DDS on loopback: set the discovery range and the Fast DDS profile before rclpy.init.

Kilted ignores ROS_LOCALHOST_ONLY; ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST plus a
loopback-only Fast DDS profile keeps every packet on 127.0.0.1 (shared/ROS_ON_PIP.md).
This module imports no rclpy, so it can run before it.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

PROFILE_NAME = "fastdds_loopback.xml"


def find_loopback_profile() -> Path | None:
    """Locate the loopback-only Fast DDS profile shipped in ``config/``.

    Looks in the source tree (editable installs and tests), then in the install
    prefixes (``share/pisml_ros/config``) of this Python and of AMENT_PREFIX_PATH.
    """
    candidates = [Path(__file__).resolve().parents[2] / "config" / PROFILE_NAME]
    prefixes = [sys.prefix] + [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    candidates += [Path(prefix) / "share" / "pisml_ros" / "config" / PROFILE_NAME for prefix in prefixes]
    return next((path for path in candidates if path.is_file()), None)


def configure_loopback_dds(environ=None) -> dict:
    """Set the loopback-only DDS environment (unless the user already chose a range/profile).

    Parameters
    ----------
    environ : mapping, optional
        Environment to update (default ``os.environ``); pass a copy to build a
        child process environment.

    Returns
    -------
    dict
        The environment that was updated.
    """
    env = os.environ if environ is None else environ
    # A deployment across machines says so explicitly (ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET, or
    # PISML_DDS_LOOPBACK=0) and is left alone; everything else stays on loopback.
    if env.get("PISML_DDS_LOOPBACK", "1") == "0":
        return env
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if env["ROS_AUTOMATIC_DISCOVERY_RANGE"] != "LOCALHOST":
        return env
    if "FASTDDS_DEFAULT_PROFILES_FILE" not in env:
        profile = find_loopback_profile()
        if profile is not None:
            env["FASTDDS_DEFAULT_PROFILES_FILE"] = str(profile)
    return env
