# Source this to use the project's tools in a shell:  source scripts/env.sh
_MEDC_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export VIRTUAL_ENV="$_MEDC_ROOT/.venv"
export PATH="$VIRTUAL_ENV/bin:$_MEDC_ROOT/tools/node_modules/.bin:$PATH"
export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export MEDC_ROOT="$_MEDC_ROOT"
# Custom ROS messages built by scripts/build_interfaces.sh
if [[ -d "$_MEDC_ROOT/ros_ws/install/medc_interfaces" ]]; then
  _iface="$_MEDC_ROOT/ros_ws/install/medc_interfaces"
  export AMENT_PREFIX_PATH="$_iface:$AMENT_PREFIX_PATH"
  export LD_LIBRARY_PATH="$_iface/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  for _sp in "$_iface"/lib/python3*/site-packages; do
    [[ -d $_sp ]] && export PYTHONPATH="$_sp${PYTHONPATH:+:$PYTHONPATH}"
  done
fi
# Keep DDS traffic on this machine.
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
unset _iface _sp
