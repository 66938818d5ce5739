#!/usr/bin/env bash
# Installs the tools the export tests load cubecal's profiles with (tests/profile.rs, tests/exports/):
#   python3-opencv                       cv2.FileStorage + cv2.projectPoints (OpenCV FileStorage YAML)
#   python3-camera-calibration-parsers   ROS's camera_info YAML parser (camera_calibration_parsers)
#   python3-mrcal                        mrcal.cameramodel + mrcal.project (.cameramodel)
#   python3-yaml                         yaml.safe_load, as Kalibr's ConfigReader reads its camchain
#                                        YAML (Kalibr itself is a ROS workspace, not installed)
#   postgresql                           initdb + pg_ctl for the throw-away cluster of the PostgreSQL
#                                        profile store's tests (tests/profile_postgres.rs,
#                                        tests/support/pg.rs; found under /usr/lib/postgresql/N/bin)
#   chromium                             headless browser for the live page's test (tests/live_page.rs,
#                                        driven over the DevTools protocol) and the report's
#                                        (tests/report_chromium.sh)
# All are Debian packages (bookworm: OpenCV 4.6, ROS parsers 1.12, mrcal 2.2) for the system
# python, /usr/bin/python3, which the tests use first (CUBECAL_PYTHON overrides). Idempotent, quiet when
# everything is present; exits non-zero if a tool still cannot be imported afterwards.
set -euo pipefail

packages=(python3-opencv python3-camera-calibration-parsers python3-mrcal python3-yaml postgresql chromium)
check='import cv2, mrcal, camera_calibration_parsers, yaml'
python="${CUBECAL_PYTHON:-/usr/bin/python3}"

have_initdb() { compgen -G '/usr/lib/postgresql/*/bin/initdb' >/dev/null; }
have_chromium() { [ -x /usr/bin/chromium ]; }
if "$python" -c "$check" >/dev/null 2>&1 && have_initdb && have_chromium; then exit 0; fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done
if [ "${#missing[@]}" -gt 0 ]; then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  echo "install-test-tools: installing ${missing[*]}" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if ! have_initdb; then
  echo "install-test-tools: no initdb under /usr/lib/postgresql/*/bin after installing postgresql" >&2
  exit 1
fi
if ! have_chromium; then
  echo "install-test-tools: no /usr/bin/chromium after installing chromium" >&2
  exit 1
fi
if ! "$python" -c "$check"; then
  echo "install-test-tools: $python still cannot import cv2, mrcal, camera_calibration_parsers and yaml" >&2
  exit 1
fi
