#!/usr/bin/env bash
# Install ggfslam and its dependencies into the current Python (CPU only; torch is pinned to 2.13.0).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# Open3D's wheel links against libusb-1.0, which bare Debian/Ubuntu machines lack.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "installing libusb-1.0-0 (needed by Open3D) ..."
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  elif command -v sudo >/dev/null && sudo -n true 2>/dev/null && command -v apt-get >/dev/null; then
    echo "installing libusb-1.0-0 (needed by Open3D) ..."
    sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "error: Open3D needs the system library libusb-1.0. Install it first, e.g." >&2
    echo "  sudo apt-get install libusb-1.0-0      (Debian/Ubuntu)" >&2
    echo "  sudo dnf install libusb1                (Fedora)" >&2
    echo "then run this script again." >&2
    exit 1
  fi
fi

# torch==2.13.0 is pinned in pyproject.toml so pip never pulls a multi-GB CUDA build by accident.
PIP_ROOT_USER_ACTION=ignore "$PY" -m pip install --disable-pip-version-check -q -e ".[dev]"
"$PY" -c "import open3d, gtsam, torch, numba, cv2; print('ggfslam installed: torch', torch.__version__, '| open3d', open3d.__version__)"
