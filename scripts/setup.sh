#!/usr/bin/env bash
# Idempotent set-up: Debian packages when missing, then a virtualenv with everything.
set -euo pipefail
venv=${1:-.venv}
export DEBIAN_FRONTEND=noninteractive

need_apt=()
command -v dot >/dev/null 2>&1 || need_apt+=(graphviz)
command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ] || need_apt+=(mosquitto)
# The web view is tested in a real browser; playwright drives Debian's chromium
# (never `playwright install`, which downloads its own).
command -v chromium >/dev/null 2>&1 || need_apt+=(chromium)
# beehave's own ROS 2 action type is generated and compiled here (build_ros_interfaces.sh).
command -v cmake >/dev/null 2>&1 || need_apt+=(cmake)
command -v g++ >/dev/null 2>&1 || need_apt+=(g++)
# The Debian packages install in the background while pip fills the virtualenv (about a
# minute): nothing needs them before the ROS build below.
apt_pid=
apt_log=$(mktemp)
trap 'rm -f "$apt_log"' EXIT
if [ ${#need_apt[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then
    { apt-get update -qq && apt-get install -y -qq "${need_apt[@]}"; } >"$apt_log" 2>&1 &
    apt_pid=$!
  else
    echo "setup: missing Debian packages (${need_apt[*]}); install them with apt-get" >&2
  fi
fi

[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/python" -m pip install -q --upgrade pip
# torch pinned in the same install: anything unpinned would pull the CUDA build.
"$venv/bin/python" -m pip install -q "torch==2.13.0" \
  -e ".[fast,ros,sim,engines,nn,mavlink,vda5050,http,record,dev]"
if [ -n "$apt_pid" ] && ! wait "$apt_pid"; then
  cat "$apt_log" >&2
  echo "setup: apt-get install ${need_apt[*]} failed" >&2
  exit 1
fi
# beehave_interfaces (the ExecuteBehavior action of beehave/execute_behavior): generated
# with rosidl from PyPI and compiled against the ROS 2 wheels just installed.
bash "$(dirname "$0")/build_ros_interfaces.sh" "$venv"
