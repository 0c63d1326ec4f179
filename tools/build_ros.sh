#!/usr/bin/env bash
# `make ros`: the ROS 2 Jazzy test environment. A venv with the Jazzy wheels, our runtime
# dependencies and cusfm_ros (editable), then a colcon build of cusfm_ros_interfaces
# (msg_schemas/) and cusfm_ros into build-ros/.
# Usage: tools/build_ros.sh PYTHON VENV [--cusfm-ros-only]
# (--cusfm-ros-only: just reinstall cusfm_ros from the working tree; `make test-ros` does this
# every time, so the tests run the current code as colcon installs it, not as it was)
set -euo pipefail
python=${1:-python3}
venv=${2:-.venv-ros}
root=$(cd "$(dirname "$0")/.." && pwd)
ws="$root/build-ros"
venv_abs=$(cd "$venv" 2>/dev/null && pwd || true)
if [ "${3:-}" = "--cusfm-ros-only" ]; then
  (cd "$ws" && PATH="$venv_abs/bin:$PATH" AMENT_PREFIX_PATH="$venv_abs" \
     colcon build --base-paths "$root" --packages-select cusfm_ros > "$ws/colcon-cusfm_ros.log" 2>&1) \
    || { tail -40 "$ws/colcon-cusfm_ros.log"; exit 1; }
  exit 0
fi
pip="$venv/bin/python -m pip --quiet --disable-pip-version-check"
$python -m venv "$venv"
$pip install -r "$root/requirements-ros.txt"
$pip install -r "$root/requirements.txt"
$pip install --no-deps --no-build-isolation -e "$root"
# The wheels' *Export.cmake files hard-code the build machine's Python and numpy include
# directories (/opt/python/cp311-cp311/...): point them at this venv's.
include=$("$venv/bin/python" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
numpy_include=$("$venv/bin/python" -c "import numpy; print(numpy.get_include())")
{ grep -rl --include="*Export.cmake" /opt/python/cp311-cp311 "$venv/share" 2>/dev/null || true; } | while read -r f; do
  sed -i "s#/opt/python/cp311-cp311/include/python3.11#$include#g;
          s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$numpy_include#g" "$f"
done
# The workspace: cusfm_ros (the repository root) and cusfm_ros_interfaces (msg_schemas/). colcon
# stops descending at the root (itself a package), so both folders are named as base paths --
# the same command README's "With ROS 2" section gives. Where tf2_msgs has no wheel, the test
# workspace builds its standard TFMessage definition as a package of its own.
mkdir -p "$ws"
venv_abs=$(cd "$venv" && pwd)
base_paths=("$root" "$root/msg_schemas")
if ! "$venv/bin/python" -c "import tf2_msgs.msg" 2>/dev/null; then
  tf2="$ws/test_src/tf2_msgs"
  mkdir -p "$tf2/msg"
  printf 'geometry_msgs/TransformStamped[] transforms\n' > "$tf2/msg/TFMessage.msg"
  cat > "$tf2/package.xml" <<'XML'
<?xml version="1.0"?>
<package format="3">
  <name>tf2_msgs</name>
  <version>0.36.0</version>
  <description>Test-workspace build of the standard tf2_msgs/TFMessage (no wheel exists).</description>
  <maintainer email="maintainers@cusfm-ros.dev">cusfm_ros maintainers</maintainer>
  <license>BSD-3-Clause</license>
  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>
  <depend>geometry_msgs</depend>
  <exec_depend>rosidl_default_runtime</exec_depend>
  <member_of_group>rosidl_interface_packages</member_of_group>
  <export><build_type>ament_cmake</build_type></export>
</package>
XML
  cat > "$tf2/CMakeLists.txt" <<'CMAKE'
cmake_minimum_required(VERSION 3.8)
project(tf2_msgs)
find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
find_package(geometry_msgs REQUIRED)
rosidl_generate_interfaces(${PROJECT_NAME} "msg/TFMessage.msg" DEPENDENCIES geometry_msgs)
ament_export_dependencies(rosidl_default_runtime)
ament_package()
CMAKE
  base_paths+=("$tf2")
fi
(cd "$ws" && PATH="$venv_abs/bin:$PATH" AMENT_PREFIX_PATH="$venv_abs" CMAKE_PREFIX_PATH="$venv_abs" \
   colcon build --base-paths "${base_paths[@]}" \
   --cmake-args -DPython3_EXECUTABLE="$venv_abs/bin/python" -DBUILD_TESTING=OFF \
   > "$ws/colcon.log" 2>&1) || { tail -40 "$ws/colcon.log"; exit 1; }
touch "$venv/.installed"
