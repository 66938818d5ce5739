#!/bin/sh
# Runs INSIDE the qemu guest (copied to the 9p share as run.sh by tests/vm/run.sh).
# vivid instances: 0 = webcam (/dev/video0), 1 = HDMI capture (/dev/video1) + HDMI output (/dev/video2)
# for loop_video, 2 = a second webcam (/dev/video3) that the unplug test disconnects.
# Pitfall: pass vivid's array parameters to modprobe directly (not through the kernel command line).
rc=0
fail() { echo "RESULT: $1 FAIL $2"; rc=1; }
modprobe vivid n_devs=3 node_types=0x1,0x101,0x1 num_inputs=1,1,1 input_types=0x0,0x3,0x0 \
  num_outputs=0,1,0 output_types=0x0,0x1,0x0 || { echo "RESULT: modprobe_vivid FAIL"; exit 1; }
ls -l /dev/video*
mkdir -p out
export CUBECAL_VIVID_WEBCAM=/dev/video0 CUBECAL_VIVID_HDMI_CAP=/dev/video1 \
  CUBECAL_VIVID_HDMI_OUT=/dev/video2 CUBECAL_VIVID_UNPLUG=/dev/video3 CUBECAL_VM_OUT=/mnt/host/out \
  CUBECAL_VM_RENDER=/mnt/host/render

echo "== cubecal devices (the real binary)"
./cubecal devices; r=$?
if [ $r = 0 ]; then echo "RESULT: cli_devices PASS exit 0"; else fail cli_devices "exit $r"; fi
./cubecal devices --json > out/devices.json; r=$?
n=$(grep -o '"path":"/dev/video[0-9]*"' out/devices.json | wc -l)
if [ $r = 0 ] && [ "$n" -ge 3 ]; then echo "RESULT: cli_devices_json PASS $n devices"; else fail cli_devices_json "exit $r, $n devices"; fi

echo "== cubecal record (the real binary)"
rm -rf /tmp/session
./cubecal record --device /dev/video0 --out /tmp/session --frames 5 --width 640 --height 480 --format YUYV --fps 30 --gain 50; r=$?
nf=$(ls /tmp/session/frame_*.png 2>/dev/null | wc -l)
if [ $r = 0 ] && [ "$nf" = 5 ] && [ -s /tmp/session/manifest.json ]; then
  echo "RESULT: cli_record PASS 5 frames + manifest"; cp -r /tmp/session out/session
else fail cli_record "exit $r, $nf frames"; fi
./cubecal record --device /dev/video2 --out /tmp/s2 --frames 1; r=$?
if [ $r = 4 ]; then echo "RESULT: cli_record_output_node PASS exit 4"; else fail cli_record_output_node "exit $r (want 4)"; fi

echo "== cargo integration test capture_vivid (static test binary)"
./capture_vivid --ignored --test-threads=1 --nocapture; r=$?
if [ $r = 0 ]; then echo "RESULT: capture_vivid PASS"; else fail capture_vivid "exit $r"; fi
exit $rc
