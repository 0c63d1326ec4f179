#!/usr/bin/env bash
# The environment of the ROS tests (`make test-ros`): the venv's Jazzy wheels and the colcon
# install of build-ros/ (cusfm_ros, cusfm_ros_interfaces, and the test workspace's tf2_msgs)
# sourced the way a user sources a workspace, discovery kept on this machine.
# Usage: tools/ros_env.sh VENV COMMAND...
set -eo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
venv=$(cd "$1" && pwd); shift
export AMENT_PREFIX_PATH="$venv"
export COLCON_CURRENT_PREFIX="$root/build-ros/install"
# shellcheck disable=SC1091
source "$root/build-ros/install/local_setup.bash"
unset COLCON_CURRENT_PREFIX
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-61}
exec "$@"
