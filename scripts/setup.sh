#!/usr/bin/env bash
# One-step set-up on a fresh Debian/Ubuntu machine: the system library Open3D needs, then the package with
# its dev extras. Idempotent; safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [ "$(id -u)" != "0" ] && command -v sudo >/dev/null 2>&1; then SUDO="sudo"; fi
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  $SUDO apt-get update -qq
  $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null
fi
python -m pip install -q --disable-pip-version-check -e '.[dev]'
