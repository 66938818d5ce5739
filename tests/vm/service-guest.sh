#!/bin/sh
# Runs INSIDE the systemd guest of tests/vm/service.sh (as the oneshot cubecal-vmtest.service, from the
# 9p share). systemd is PID 1 and udev is the real systemd-udevd; cubecal was installed by
# deploy/install.sh (unit, rules, example config, binary). Loading vivid must make udev start
# cubecal@video0.service, which runs `cubecal serve` on the HDMI capture node with the GRBL simulator on
# a pseudo-terminal as its turntable; its READY/STATUS notifications are followed here; unloading vivid
# must stop the unit.
rc=0
fail() { echo "RESULT: $1 FAIL $2"; rc=1; }
pass() { echo "RESULT: $1 PASS $2"; }
unit=cubecal@video0.service
prop() { systemctl show -P "$2" "$1"; }
# wait_for SECONDS COMMAND...: poll every 0.2 s until COMMAND succeeds
wait_for() { t=$1; shift; i=0; while [ $i -lt $((t * 5)) ]; do "$@" && return 0; sleep 0.2; i=$((i + 1)); done; return 1; }

pid1=$(readlink /proc/1/exe)
case "$pid1" in */systemd) pass systemd_pid1 "$pid1" ;; *) fail systemd_pid1 "$pid1" ;; esac
pidof systemd-udevd >/dev/null && pass udevd_running "" || fail udevd_running ""

# The operator's config: the installed example with a shorter plan (TCG is slow).
conf=/etc/cubecal/station.toml
[ -f $conf ] && pass config_installed "" || fail config_installed "$conf missing"
sed -i 's/^poses = .*/poses = 4/; s/^min_views = .*/min_views = 2/; s/^held_out = .*/held_out = 0/' $conf

# vivid with one HDMI capture node (video0) looped from one HDMI output node (video1)
modprobe vivid n_devs=1 node_types=0x101 num_inputs=1 input_types=0x3 num_outputs=1 output_types=0x1 ||
  { fail modprobe_vivid ""; exit 1; }
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
last=""; was_active=""; i=0
while [ $i -lt 1500 ]; do
  s=$(prop $unit StatusText); st=$(prop $unit ActiveState)
  [ "$s" != "$last" ] && echo "STATUS: $s" && last=$s
  [ "$st" = active ] && [ -z "$was_active" ] && was_active=$(cut -d' ' -f1 /proc/uptime) && echo "unit active (READY=1) at uptime $was_active"
  [ "$st" = failed ] && break
  [ -n "$was_active" ] && [ "$(prop $unit MainPID)" = 0 ] && break
  sleep 0.2; i=$((i + 1))
done
s=$(prop $unit StatusText); [ "$s" != "$last" ] && echo "STATUS: $s"
[ -n "$was_active" ] && pass ready_notify "active after READY=1" || fail ready_notify "never active"
echo "unit: $(prop $unit ActiveState)/$(prop $unit SubState) result=$(prop $unit Result) exit=$(prop $unit ExecMainStatus) restarts=$(prop $unit NRestarts) watchdog=$(prop $unit WatchdogUSec)"
case "$(prop $unit StatusText)" in
  "verdict "*) pass verdict_in_status "$(prop $unit StatusText | cut -c1-60)" ;;
  *) fail verdict_in_status "'$(prop $unit StatusText)'" ;;
esac
systemctl status --no-pager -l -n 0 $unit | sed 's/^/  | /'
ls -lR /var/lib/cubecal/ 2>&1 | head -30 | sed 's/^/  state| /'

# removing the device stops the unit (BindsTo=dev-video0.device)
rmmod vivid || fail rmmod_vivid ""
stopped() { [ "$(prop $unit ActiveState)" = inactive ] || [ "$(prop $unit ActiveState)" = failed ]; }
if wait_for 20 stopped; then pass unplug_stops_unit "$(prop $unit ActiveState)"
else fail unplug_stops_unit "$(prop $unit ActiveState)/$(prop $unit SubState)"; fi
journalctl -b --no-pager -o short-monotonic -u $unit | tail -80 | sed 's/^/  j| /'
exit $rc
