#!/usr/bin/env bash
# Static checks of the station service's systemd unit and udev rules (called from .ci/run):
#   1. `systemd-analyze verify` of deploy/systemd/cubecal@.service is clean;
#   2. `systemd-analyze security --offline=true` prints the unit's exposure, which must be <= 2.0, with
#      and without the live page's drop-in (deploy/systemd/live-page.conf);
#   3. `udevadm test` runs the rules against fake sysfs devices (a USB V4L2 capture node, a USB V4L2
#      output-only node, a UVC metadata node, an FTDI USB-serial adapter) and the resulting properties
#      must be: capture node -> TAG systemd + SYSTEMD_WANTS=cubecal@video0.service, the others not;
#      adapter -> /dev/cubecal-turntable and group dialout.
# Installs systemd and udev from Debian when absent. Needs root (a private mount namespace for step 3).
# Exit 0 pass, 1 fail, 2 setup error.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
unit_src=deploy/systemd/cubecal@.service
max_exposure=2.0

missing=()
command -v systemd-analyze >/dev/null || missing+=(systemd)
command -v udevadm >/dev/null || missing+=(udev)
command -v unshare >/dev/null || missing+=(util-linux)
if [ "${#missing[@]}" -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "service_static: installing ${missing[*]}" >&2
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null \
    || { echo "service_static: SETUP ERROR: cannot install ${missing[*]}"; exit 2; }
fi

work=$(mktemp -d)
trap '[ -n "${KEEP_WORK:-}" ] || rm -rf "$work"' EXIT
fail=0

# --- 1. systemd-analyze verify -------------------------------------------------------------------
# verify checks that ExecStart's binary exists and is executable: point it at the binary just built
# (same unit otherwise; the installed unit keeps /usr/local/bin/cubecal, where deploy/install.sh puts it).
bin="${CARGO_TARGET_DIR:-$root/target}/debug/cubecal"
case "$bin" in /*) ;; *) bin="$root/$bin" ;; esac
if [ ! -x "$bin" ]; then cargo build --locked --quiet --bin cubecal; fi
grep -q '^ExecStart=/usr/local/bin/cubecal serve ' "$unit_src" \
  || { echo "service_static: FAIL: $unit_src ExecStart is not /usr/local/bin/cubecal serve ..."; exit 1; }
mkdir -p "$work/unit"
sed "s|^ExecStart=/usr/local/bin/cubecal |ExecStart=$bin |" "$unit_src" > "$work/unit/cubecal@.service"
echo "== systemd-analyze verify cubecal@video0.service"
if (cd "$work/unit" && systemd-analyze verify --man=no "cubecal@video0.service") > "$work/verify.log" 2>&1 \
   && ! grep -q . "$work/verify.log"; then
  echo "RESULT: unit_verify PASS (no warnings)"
else
  cat "$work/verify.log"; echo "RESULT: unit_verify FAIL"; fail=1
fi

# --- 2. systemd-analyze security -----------------------------------------------------------------
echo "== systemd-analyze security --offline=true cubecal@video0.service"
(cd "$work/unit" && systemd-analyze security --offline=true --no-pager "cubecal@video0.service") \
  > "$work/security.log" 2>&1 || true
grep -v '✓' "$work/security.log" || true
exposure=$(sed -n 's/.*Overall exposure level for cubecal@video0.service: \([0-9.]*\).*/\1/p' "$work/security.log")
if [ -z "$exposure" ]; then
  cat "$work/security.log"; echo "RESULT: unit_security FAIL no exposure figure"; fail=1
elif awk -v e="$exposure" -v m="$max_exposure" 'BEGIN { exit !(e <= m) }'; then
  echo "RESULT: unit_security PASS exposure $exposure (limit $max_exposure)"
else
  echo "RESULT: unit_security FAIL exposure $exposure above $max_exposure"; fail=1
fi

# --- 2b. the same with the live page's drop-in (deploy/systemd/live-page.conf) -------------------
# A drop-in's settings as if appended to the unit: the same file with the drop-in at its end.
echo "== with the live page: deploy/systemd/live-page.conf"
mkdir -p "$work/unit-live"
{ cat "$work/unit/cubecal@.service"; sed "s|/usr/local/bin/cubecal |$bin |" deploy/systemd/live-page.conf; } \
  > "$work/unit-live/cubecal@.service"
if (cd "$work/unit-live" && systemd-analyze verify --man=no "cubecal@video0.service") > "$work/verify-live.log" 2>&1 \
   && ! grep -q . "$work/verify-live.log"; then
  echo "RESULT: unit_live_verify PASS (no warnings)"
else
  cat "$work/verify-live.log"; echo "RESULT: unit_live_verify FAIL"; fail=1
fi
(cd "$work/unit-live" && systemd-analyze security --offline=true --no-pager "cubecal@video0.service") \
  > "$work/security-live.log" 2>&1 || true
grep -v '✓' "$work/security-live.log" || true
exposure=$(sed -n 's/.*Overall exposure level for cubecal@video0.service: \([0-9.]*\).*/\1/p' "$work/security-live.log")
grep -q -- '--http 127.0.0.1:' "$work/unit-live/cubecal@.service" \
  || { echo "RESULT: unit_live_security FAIL the drop-in does not bind the page to 127.0.0.1"; fail=1; }
if [ -z "$exposure" ]; then
  cat "$work/security-live.log"; echo "RESULT: unit_live_security FAIL no exposure figure"; fail=1
elif awk -v e="$exposure" -v m="$max_exposure" 'BEGIN { exit !(e <= m) }'; then
  echo "RESULT: unit_live_security PASS exposure $exposure (limit $max_exposure)"
else
  echo "RESULT: unit_live_security FAIL exposure $exposure above $max_exposure"; fail=1
fi

# --- 3. udev rules under udevadm test ------------------------------------------------------------
# Runs in a private mount namespace: a fake /sys (SYSTEMD_DEVICE_VERIFY_SYSFS=0 lets sd-device accept a
# tmpfs there), tmpfs over /dev and /run (udevadm test creates links and database entries), only the
# distribution's rules plus ours, and a stand-in for v4l_id (which would open the node and ask
# VIDIOC_QUERYCAP) reporting the capabilities the fake node is given. The real 60-persistent-v4l.rules
# imports it, as on a real machine.
echo "== udevadm test udev/*.rules (fake sysfs devices)"
cat > "$work/udev-inner.sh" <<'INNER'
set -eu
rules="$1"; work="$2"
mkdir -p "$work/realdev" && mount --bind /dev "$work/realdev"
mount -t tmpfs none /sys
mount -t tmpfs none /dev
touch /dev/null && mount --bind "$work/realdev/null" /dev/null
mount -t tmpfs none /run
mkdir -p /etc/udev/rules.d && mount -t tmpfs none /etc/udev/rules.d
cp "$rules"/*.rules /etc/udev/rules.d/
cat > "$work/v4l_id" <<'EOS'
#!/bin/sh
# stand-in for v4l_id: capabilities of the fake node from a file named after it
echo ID_V4L_VERSION=2
echo ID_V4L_PRODUCT=fake
echo "ID_V4L_CAPABILITIES=$(cat "/sys/fake-caps/$(basename "$1")")"
EOS
chmod +x "$work/v4l_id"
mount --bind "$work/v4l_id" /usr/lib/udev/v4l_id
mkdir -p /sys/bus/usb /sys/class/tty /sys/class/video4linux /sys/fake-caps
usb=/sys/devices/pci0000:00/0000:00:14.0/usb1/1-1
mkdir -p "$usb"; echo 0403 > "$usb/idVendor"; echo 6001 > "$usb/idProduct"
printf 'DEVTYPE=usb_device\n' > "$usb/uevent"; ln -s /sys/bus/usb "$usb/subsystem"
node() { # node IFACE SUBSYS KERNEL MAJOR MINOR [CAPS]
  d="$usb/$1/$2/$3"; [ "$2" = tty ] && d="$usb/$1/$3/tty/$3"
  mkdir -p "$d"; printf 'MAJOR=%s\nMINOR=%s\nDEVNAME=%s\n' "$4" "$5" "$3" > "$d/uevent"
  ln -s "/sys/class/$2" "$d/subsystem"
  [ "$2" = video4linux ] && { echo 0 > "$d/index"; echo "$6" > "/sys/fake-caps/$3"; }
  echo "$d"
}
export SYSTEMD_DEVICE_VERIFY_SYSFS=0
t() { udevadm test --action=add "$1" 2>"$work/$2.err" | sed -n '/^[A-Z0-9_]*=/p' > "$work/$2.props"; }
t "$(node 1-1:1.0 video4linux video0 81 0 ':capture:')" capture
t "$(node 1-1:1.0 video4linux video1 81 1 ':')" metadata
t "$(node 1-1:1.1 video4linux video2 81 2 ':video_output:')" output
t "$(node 1-1:1.2 tty ttyUSB0 188 0)" serial
INNER
if unshare -m sh "$work/udev-inner.sh" "$root/udev" "$work" > "$work/udev.log" 2>&1; then
  check() { # check NAME FILE WANT-REGEX present|absent
    if grep -Eq "$3" "$work/$2.props"; then found=present; else found=absent; fi
    if [ "$found" = "$4" ]; then echo "RESULT: $1 PASS"; else
      echo "RESULT: $1 FAIL ($3 $found in $2)"; cat "$work/$2.props"; grep -i cubecal "$work/$2.err" || true; fail=1
    fi
  }
  check udev_v4l_id_stand_in capture '^ID_V4L_CAPABILITIES=:capture:$' present
  check udev_capture_wants_unit capture '^SYSTEMD_WANTS=(.* )?cubecal@video0\.service( |$)' present
  check udev_capture_tag_systemd capture '^TAGS=.*:systemd:' present
  check udev_metadata_no_unit metadata '^SYSTEMD_WANTS=.*cubecal@' absent
  check udev_output_no_unit output '^SYSTEMD_WANTS=.*cubecal@' absent
  check udev_turntable_link serial '^DEVLINKS=(.* )?/dev/cubecal-turntable( |$)' present
  dialout=$(getent group dialout | cut -d: -f3)
  if [ -n "$dialout" ] && grep -Eq "99-cubecal\.rules:[0-9]+ GROUP $dialout\$" "$work/serial.err"; then
    echo "RESULT: udev_turntable_group PASS"
  else
    grep -i cubecal "$work/serial.err" || true; echo "RESULT: udev_turntable_group FAIL"; fail=1
  fi
  # A rule file that udev cannot parse is logged with its file:line at load time.
  if grep -hE 'cubecal[^ ]*\.rules:[0-9]+.*(Invalid|invalid|Unknown|unknown|ignor)' "$work"/*.err; then
    echo "RESULT: udev_rules_parse FAIL"; fail=1
  else
    echo "RESULT: udev_rules_parse PASS"
  fi
else
  cat "$work/udev.log"; echo "service_static: SETUP ERROR: udevadm test in a mount namespace failed"; exit 2
fi

if [ "$fail" = 0 ]; then echo "service_static: PASS"; else echo "service_static: FAIL"; fi
exit "$fail"
