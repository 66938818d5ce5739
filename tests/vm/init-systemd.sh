#!/bin/sh
# Initramfs /init of the systemd guest (tests/vm/service.sh): load virtio-blk and ext4, mount the root
# file system image (/dev/vda, a throw-away snapshot), hand over to systemd as PID 1.
export PATH=/bin:/sbin
mount -t proc proc /proc; mount -t sysfs sysfs /sys; mount -t devtmpfs devtmpfs /dev
echo "VMTEST: initramfs uptime=$(cut -d' ' -f1 /proc/uptime)"
for m in virtio_pci virtio_blk crc32c_generic ext4; do modprobe "$m" || echo "VMTEST: modprobe $m failed"; done
i=0; while [ ! -b /dev/vda ] && [ $i -lt 50 ]; do sleep 0.1; i=$((i + 1)); done
mkdir -p /newroot
if ! mount -t ext4 -o rw /dev/vda /newroot; then
  echo "VMTEST-EXIT: 2 (cannot mount the root image)"; poweroff -f
fi
umount /proc /sys
mount --move /dev /newroot/dev
exec switch_root /newroot /sbin/init
