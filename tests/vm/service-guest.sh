#!/bin/sh
# Runs INSIDE the systemd guest of tests/vm/service.sh (as the oneshot cubecal-vmtest.service, from the
# 9p share). systemd is PID 1 and udev is the real systemd-udevd; cubecal was installed by
# deploy/install.sh (unit, rules, config, binary).
rc=0
fail() { echo "RESULT: $1 FAIL $2"; rc=1; }
pass() { echo "RESULT: $1 PASS $2"; }
unit=cubecal@video0.service
prop() { systemctl show -P "$2" "$1"; }
# wait_for SECONDS COMMAND...: poll every 0.2 s until COMMAND succeeds
wait_for() { t=$1; shift; i=0; while [ $i -lt $((t * 5)) ]; do "$@" && return 0; sleep 0.2; i=$((i + 1)); done; return 1; }

pid1=$(readlink /proc/1/exe)
case "$pid1" in */systemd) pass systemd_pid1 "$pid1" ;; *) fail systemd_pid1 "$pid1" ;; esac
state=$(systemctl is-system-running)
echo "system state: $state"; systemctl --failed --no-legend --plain | sed 's/^/  failed unit: /'
pidof systemd-udevd >/dev/null && pass udevd_running "" || fail udevd_running ""

# vivid with one HDMI capture node (video0) looped from one HDMI output node (video1)
modprobe vivid n_devs=1 node_types=0x101 num_inputs=1 input_types=0x3 num_outputs=1 output_types=0x1 ||
  { fail modprobe_vivid ""; exit 1; }
udevadm settle -t 30
ls -l /dev/video* /dev/v4l 2>/dev/null
started() { [ "$(prop $unit ExecMainStartTimestampMonotonic)" != 0 ] || [ "$(prop $unit ActiveState)" != inactive ]; }
if wait_for 30 started; then pass udev_started_unit "$(prop $unit ActiveState)/$(prop $unit SubState)"
else fail udev_started_unit "$(prop $unit ActiveState)"; fi
wants=$(udevadm info -q property -n /dev/video0 | sed -n 's/^SYSTEMD_WANTS=//p')
[ "$wants" = "$unit" ] && pass udev_wants "$wants" || fail udev_wants "'$wants'"
[ "$(prop cubecal@video1.service ExecMainStartTimestampMonotonic)" = 0 ] &&
  pass output_node_no_unit "" || fail output_node_no_unit "cubecal@video1 was started"
sleep 3
systemctl status --no-pager -l $unit | sed 's/^/  | /'
echo "STATUS: $(prop $unit StatusText)"
echo "unit result: $(prop $unit Result) exit=$(prop $unit ExecMainStatus) restarts=$(prop $unit NRestarts)"

# removing the device stops the unit (BindsTo=dev-video0.device)
rmmod vivid || fail rmmod_vivid ""
stopped() { [ "$(prop $unit ActiveState)" = inactive ] || [ "$(prop $unit ActiveState)" = failed ]; }
if wait_for 20 stopped; then pass unplug_stops_unit "$(prop $unit ActiveState)"
else fail unplug_stops_unit "$(prop $unit ActiveState)/$(prop $unit SubState)"; fi
journalctl -b --no-pager -o short-monotonic -u $unit | tail -30 | sed 's/^/  j| /'
exit $rc
