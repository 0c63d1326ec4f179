#!/usr/bin/env bash
# The environment of the ROS tests (`make test-ros`): the built interface package on the
# paths, discovery kept on this machine. Usage: tools/ros_env.sh VENV COMMAND...
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv=$(cd "$1" && pwd); shift
interfaces="$root/build-ros/install/cusfm_ros_interfaces"
export AMENT_PREFIX_PATH="$interfaces:$venv"
export PYTHONPATH="$interfaces/lib/python3.11/site-packages${PYTHONPATH:+:$PYTHONPATH}"
export LD_LIBRARY_PATH="$interfaces/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-61}
exec "$@"
