#!/bin/sh
# Runs INSIDE the systemd guest of tests/vm/service.sh (as the oneshot cubecal-vmtest.service, from the
# 9p share). systemd is PID 1 and udev is the real systemd-udevd; cubecal was installed by
# deploy/install.sh (unit, rules, example config, binary).
#
# One loop, every part real: `cubecal turntable simulate --feed` serves a GRBL simulator on a
# pseudo-terminal (linked as /dev/cubecal-turntable, the unit's turntable port) and writes the rig,
# rendered at the angle its simulator reports, to vivid's HDMI output; vivid loops that output into
# its HDMI capture node. Loading vivid makes udev start cubecal@video0.service, whose `cubecal serve`
# captures through V4L2, drives the simulator over the serial protocol, and must end with a passing
# profile in /var/lib/cubecal. Its READY/STATUS notifications and watchdog pings are followed here;
# unloading vivid must stop the unit.
rc=0
fail() { echo "RESULT: $1 FAIL $2"; rc=1; }
pass() { echo "RESULT: $1 PASS $2"; }
unit=cubecal@video0.service
prop() { systemctl show -P "$2" "$1"; }
# wait_for SECONDS COMMAND...: poll every 0.2 s until COMMAND succeeds
wait_for() { t=$1; shift; i=0; while [ $i -lt $((t * 5)) ]; do "$@" && return 0; sleep 0.2; i=$((i + 1)); done; return 1; }
uptime_s() { cut -d' ' -f1 /proc/uptime; }

pid1=$(readlink /proc/1/exe)
case "$pid1" in */systemd) pass systemd_pid1 "$pid1" ;; *) fail systemd_pid1 "$pid1" ;; esac
pidof systemd-udevd >/dev/null && pass udevd_running "" || fail udevd_running ""

# The operator's config: the installed example is replaced by this test's (tests/vm/station.toml).
conf=/etc/cubecal/station.toml
[ -f $conf ] && pass config_installed "" || fail config_installed "$conf missing"
cp /mnt/host/station.toml $conf

# The turntable and the camera's picture: simulator + feeder, started before vivid exists (the
# feeder waits for vivid's nodes; the unit that udev starts must find its turntable port).
link=/dev/cubecal-turntable
/usr/local/bin/cubecal turntable simulate -v --protocol grbl --axis A --degrees-per-unit 0.5 \
  --speed-deg-s 90 --accel-deg-s2 360 --link $link \
  --feed /dev/video1 --vivid-loop /dev/video0 --station-config $conf > /tmp/simulate.log 2>&1 &
sim=$!
if wait_for 30 test -e $link; then
  # what udev's GROUP="dialout" does for a real USB-serial adapter (udev/99-cubecal.rules)
  pts=$(readlink -f $link); chgrp dialout "$pts"; chmod 0660 "$pts"
  pass turntable_link "$link -> $pts"
else fail turntable_link "no $link"; cat /tmp/simulate.log; fi

# vivid with one HDMI capture node (video0) looped from one HDMI output node (video1)
modprobe vivid n_devs=1 node_types=0x101 num_inputs=1 input_types=0x3 num_outputs=1 output_types=0x1 ||
  { fail modprobe_vivid ""; exit 1; }
echo "vivid loaded at uptime $(uptime_s)"
udevadm settle -t 30
started() { [ "$(prop $unit ExecMainStartTimestampMonotonic)" != 0 ] || [ "$(prop $unit ActiveState)" != inactive ]; }
if wait_for 30 started; then pass udev_started_unit "$(prop $unit ActiveState)/$(prop $unit SubState)"
else fail udev_started_unit "$(prop $unit ActiveState)"; fi
wants=$(udevadm info -q property -n /dev/video0 | sed -n 's/^SYSTEMD_WANTS=//p')
[ "$wants" = "$unit" ] && pass udev_wants "$wants" || fail udev_wants "'$wants'"
[ "$(prop cubecal@video1.service ExecMainStartTimestampMonotonic)" = 0 ] &&
  pass output_node_no_unit "" || fail output_node_no_unit "cubecal@video1 was started"

# Follow the STATUS= lines from the start until the run ends (the main process exits; RemainAfterExit
# keeps the unit and its status). Type=notify: the unit turns active only once serve sent READY=1.
# WatchdogTimestampMonotonic is the time of the last WATCHDOG=1 systemd received: its largest step is
# the longest the station went without pinging (to within this loop's polling).
last=""; was_active=""; i=0; wd_last=""; wd_n=0; wd_gap=0
while [ $i -lt 6000 ]; do
  s=$(prop $unit StatusText); st=$(prop $unit ActiveState)
  [ "$s" != "$last" ] && echo "STATUS: [$(uptime_s)] $s" && last=$s
  [ "$st" = active ] && [ -z "$was_active" ] && was_active=$(uptime_s) && echo "unit active (READY=1) at uptime $was_active"
  wd=$(prop $unit WatchdogTimestampMonotonic)
  if [ -n "$wd" ] && [ "$wd" != 0 ] && [ "$wd" != "$wd_last" ]; then
    if [ -n "$wd_last" ]; then g=$(( (wd - wd_last) / 1000 )); [ $g -gt $wd_gap ] && wd_gap=$g; fi
    wd_last=$wd; wd_n=$((wd_n + 1))
  fi
  [ "$st" = failed ] && break
  [ -n "$was_active" ] && [ "$(prop $unit MainPID)" = 0 ] && break
  sleep 0.2; i=$((i + 1))
done
s=$(prop $unit StatusText); [ "$s" != "$last" ] && echo "STATUS: [$(uptime_s)] $s"
[ -n "$was_active" ] && pass ready_notify "active after READY=1" || fail ready_notify "never active"
wd_usec=$(prop $unit WatchdogUSec)
echo "watchdog: WatchdogUSec=$wd_usec, $wd_n distinct ping times seen, largest gap between them ${wd_gap} ms"
echo "unit: $(prop $unit ActiveState)/$(prop $unit SubState) result=$(prop $unit Result) exit=$(prop $unit ExecMainStatus) restarts=$(prop $unit NRestarts)"
[ "$(prop $unit NRestarts)" = 0 ] && [ "$(prop $unit Result)" = success ] &&
  pass unit_ran_once "exit $(prop $unit ExecMainStatus), no restart, no watchdog timeout" ||
  fail unit_ran_once "result=$(prop $unit Result) restarts=$(prop $unit NRestarts)"
case "$(prop $unit StatusText)" in
  "verdict PASS"*) pass verdict_pass_in_status "$(prop $unit StatusText | cut -c1-80)" ;;
  *) fail verdict_pass_in_status "'$(prop $unit StatusText)'" ;;
esac
systemctl status --no-pager -l -n 0 $unit | sed 's/^/  | /'

# The profile: in the unit's state directory, shown by the CLI an operator would use.
store=/var/lib/cubecal/profiles
ids=$(ls $store 2>/dev/null | grep -v '^\.' )
if [ -n "$ids" ] && ls $store/*/current.json >/dev/null 2>&1; then
  pass profile_written "$(ls $store/*/current.json)"
else fail profile_written "none in $store"; fi
for id in $ids; do
  echo "== cubecal profile show $id"
  /usr/local/bin/cubecal profile show --store $store "$id" 2>&1 | sed 's/^/  profile| /'
done
ls -lR /var/lib/cubecal/ 2>&1 | grep -v 'frame_' | head -40 | sed 's/^/  state| /'

# The simulator and feeder: stopped (vivid cannot be unloaded while the feeder holds its output).
kill -TERM $sim 2>/dev/null; wait $sim; echo "simulate exited with $?"
grep -E 'render|feed|WARN|ERROR' /tmp/simulate.log | tail -20 | sed 's/^/  sim| /'

# removing the device stops the unit (BindsTo=dev-video0.device)
rmmod vivid || fail rmmod_vivid ""
stopped() { [ "$(prop $unit ActiveState)" = inactive ] || [ "$(prop $unit ActiveState)" = failed ]; }
if wait_for 20 stopped; then pass unplug_stops_unit "$(prop $unit ActiveState)"
else fail unplug_stops_unit "$(prop $unit ActiveState)/$(prop $unit SubState)"; fi
journalctl -b --no-pager -o short-monotonic -u $unit | tail -80 | sed 's/^/  j| /'
exit $rc
