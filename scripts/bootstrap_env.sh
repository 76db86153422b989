#!/usr/bin/env bash
# Create (or bring up to date) the project's virtual environment in .venv:
#   1. pinned pip install of ROS 2 Kilted wheels, torch (CPU), torchdiffeq, pysindy, ... ;
#   2. build + install the pisml_msgs interface package (msg_defs/) into the venv prefix;
#   3. editable install of pisml_ros (console scripts pisml, pisml-measurement, ...).
# Each step re-runs only when its inputs changed (hash stamps in .venv), so a second run takes
# about a second. Facts behind the odd steps: ../shared/ROS_ON_PIP.md.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${PISML_VENV:-$ROOT/.venv}"
PYTHON="${PYTHON:-python3}"
cd "$ROOT"

log() { printf '[env] %s\n' "$*" >&2; }
hash_of() { cat "$@" | sha256sum | cut -c1-16; }

if [ ! -x "$VENV/bin/python" ]; then
  log "creating virtual environment $VENV"
  "$PYTHON" -m venv "$VENV"
fi
VPY="$VENV/bin/python"

# 1. Python dependencies (torch pinned in the same pip command as torchdiffeq: see requirements.txt)
req_hash=$(hash_of scripts/requirements.txt)
if [ "$(cat "$VENV/.stamp-requirements" 2>/dev/null)" != "$req_hash" ]; then
  log "installing pinned dependencies (first time: 2-3 minutes)"
  "$VPY" -m pip install --disable-pip-version-check -q -r scripts/requirements.txt 2>&1 \
    | grep -v "is ignored: it is neither a file nor a directory" >&2 || true
  "$VPY" -c "import rclpy, torch, torchdiffeq, pysindy, rosbags, scipy, sympy, matplotlib" \
    || { log "dependency install failed"; exit 1; }
  rm -f "$VENV/.stamp-msgs"
  echo "$req_hash" > "$VENV/.stamp-requirements"
fi

# 2. pisml_msgs (CMake + rosidl against the wheels)
msg_hash=$(hash_of msg_defs/CMakeLists.txt msg_defs/package.xml msg_defs/msg/* msg_defs/action/*)
if [ "$(cat "$VENV/.stamp-msgs" 2>/dev/null)" != "$msg_hash" ]; then
  log "building pisml_msgs into the venv (about 30 s)"
  py_inc=$("$VPY" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
  np_inc=$("$VPY" -c "import numpy; print(numpy.get_include())")
  # The wheels' CMake exports carry their build machine's include paths: point them at ours.
  grep -rlZ '/opt/python/cp311-cp311' "$VENV/share" --include='*.cmake' 2>/dev/null \
    | xargs -0 -r sed -i \
        -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#${np_inc}#g" \
        -e "s#/opt/python/cp311-cp311/include/python3.11#${py_inc}#g" || true
  build="$ROOT/build/pisml_msgs"
  rm -rf "$build"; mkdir -p "$ROOT/build"
  export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
  cmake -S msg_defs -B "$build" -DCMAKE_INSTALL_PREFIX="$VENV" -DPython3_EXECUTABLE="$VPY" \
        -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release > "$build.log" 2>&1 \
    && cmake --build "$build" -j 2 >> "$build.log" 2>&1 \
    && cmake --install "$build" >> "$build.log" 2>&1 \
    || { log "pisml_msgs build failed; see $build.log"; tail -n 30 "$build.log" >&2; exit 1; }
  "$VPY" -c "from pisml_msgs.msg import MeasurementBatch; from pisml_msgs.action import Identify" \
    || { log "pisml_msgs built but does not import"; exit 1; }
  echo "$msg_hash" > "$VENV/.stamp-msgs"
fi

# 3. the package itself, editable
pkg_hash=$(hash_of setup.py setup.cfg package.xml)
if [ "$(cat "$VENV/.stamp-package" 2>/dev/null)" != "$pkg_hash" ]; then
  log "installing pisml_ros (editable)"
  "$VPY" -m pip install --disable-pip-version-check -q --no-deps --no-build-isolation -e . >&2
  echo "$pkg_hash" > "$VENV/.stamp-package"
fi
