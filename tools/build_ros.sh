#!/usr/bin/env bash
# `make ros`: the ROS 2 Jazzy test environment. A venv with the Jazzy wheels, our runtime
# dependencies and cusfm_ros (editable), then a colcon build of cusfm_ros_interfaces
# (msg_schemas/) into build-ros/. Usage: tools/build_ros.sh PYTHON VENV
set -euo pipefail
python=${1:-python3}
venv=${2:-.venv-ros}
root=$(cd "$(dirname "$0")/.." && pwd)
pip="$venv/bin/python -m pip --quiet --disable-pip-version-check"
$python -m venv "$venv"
$pip install -r "$root/requirements-ros.txt"
$pip install -r "$root/requirements.txt"
$pip install --no-deps --no-build-isolation -e "$root"
# The wheels' *Export.cmake files hard-code the build machine's Python and numpy include
# directories (/opt/python/cp311-cp311/...): point them at this venv's.
include=$("$venv/bin/python" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
numpy_include=$("$venv/bin/python" -c "import numpy; print(numpy.get_include())")
grep -rl --include='*Export.cmake' /opt/python/cp311-cp311 "$venv/share" 2>/dev/null | while read -r f; do
  sed -i "s#/opt/python/cp311-cp311/include/python3.11#$include#g;
          s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$numpy_include#g" "$f"
done
# colcon stops at the repository root (itself a package): the workspace links the interface
# package under its own name.
ws="$root/build-ros"
mkdir -p "$ws/src"
ln -sfn "$root/msg_schemas" "$ws/src/cusfm_ros_interfaces"
venv_abs=$(cd "$venv" && pwd)
(cd "$ws" && PATH="$venv_abs/bin:$PATH" AMENT_PREFIX_PATH="$venv_abs" CMAKE_PREFIX_PATH="$venv_abs" \
   colcon build --packages-select cusfm_ros_interfaces \
   --cmake-args -DPython3_EXECUTABLE="$venv_abs/bin/python" -DBUILD_TESTING=OFF \
   > "$ws/colcon.log" 2>&1) || { tail -40 "$ws/colcon.log"; exit 1; }
touch "$venv/.installed"
