#!/usr/bin/env bash
# Installs the system packages cubecal's build needs on a fresh Debian machine:
#   libclang-dev (bindgen for the v4l crate), libudev-dev + pkg-config (serialport).
# Idempotent, and quiet when everything is already present.
set -euo pipefail

packages=(libclang-dev libudev-dev pkg-config)
missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done
[ "${#missing[@]}" -eq 0 ] && exit 0

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
echo "install-deps: installing ${missing[*]}" >&2
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
