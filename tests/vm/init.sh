#!/bin/sh
# Guest /init (copied into the initramfs by tests/vm/run.sh): mount pseudo file systems, arm a watchdog,
# mount the host share (9p tag host0) on /mnt/host, run /mnt/host/run.sh, print VMTEST-EXIT, power off.
export PATH=/bin:/sbin
mount -t proc proc /proc; mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev; mount -t tmpfs tmpfs /tmp
T=$(sed -n 's/.*vmtest_timeout=\([0-9]*\).*/\1/p' /proc/cmdline)
( sleep "${T:-180}"; echo "VMTEST-EXIT: 124 (guest watchdog after ${T:-180}s)"; poweroff -f ) &
echo "VMTEST: init start uptime=$(cut -d' ' -f1 /proc/uptime)"
rc=1
# pitfall: 9p needs virtio_pci loaded first
if modprobe virtio_pci && modprobe 9pnet_virtio && modprobe 9p &&
   mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000 host0 /mnt/host; then
  if [ -x /mnt/host/run.sh ]; then cd /mnt/host && ./run.sh; rc=$?; cd /; else echo "VMTEST: no run.sh"; fi
else
  echo "VMTEST: host share not mounted"
fi
echo "VMTEST-EXIT: $rc uptime=$(cut -d' ' -f1 /proc/uptime)"
umount /mnt/host 2>/dev/null; sync
poweroff -f
