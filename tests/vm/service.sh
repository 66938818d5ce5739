#!/bin/bash
# tests/vm/service.sh — the station service under the REAL udev and systemd, in a qemu guest.
#
# Boots a minimal Debian bookworm root file system (mmdebstrap from Debian's packages: systemd as
# PID 1, udev, kmod; cached) with Debian's kernel (shared with tests/vm/run.sh), installs cubecal into
# it with deploy/install.sh (DESTDIR), and runs tests/vm/service-guest.sh as a oneshot unit of the
# guest: start the GRBL simulator with its feeder (`cubecal turntable simulate --feed`: the rig rendered
# at the simulator's angle, written to vivid's output and looped into its capture) -> load vivid ->
# udev starts cubecal@videoN.service -> the station calibrates through V4L2 and the serial protocol ->
# a passing profile in /var/lib/cubecal -> unload vivid -> the unit stops. The station config is
# tests/vm/station.toml. Exit 0 PASS, 1 FAIL, 2 setup error.
#
# usage: tests/vm/service.sh [all|rootfs|build|boot]   (default: all)
# env:   CUBECAL_VM_WORK (default $CARGO_TARGET_DIR/vm), VM_TIMEOUT=900 (guest watchdog, s),
#        CUBECAL_VM_BIN: a static cubecal to install (default: the one tests/vm/run.sh built, else build it)
set -euo pipefail
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target}
case "$TARGET_DIR" in /*) ;; *) TARGET_DIR=$ROOT/$TARGET_DIR ;; esac
WORK=${CUBECAL_VM_WORK:-$TARGET_DIR/vm}
VM_TIMEOUT=${VM_TIMEOUT:-900}
SUITE=bookworm
MIRROR=http://deb.debian.org/debian
GUEST_PKGS=systemd-sysv,udev,kmod
export DEBIAN_FRONTEND=noninteractive
mkdir -p "$WORK"
T0=$SECONDS
log() { echo "[vm-service +$((SECONDS - T0))s] $*" >&2; }
die() { log "SETUP ERROR: $*"; exit 2; }
timed() { local s=$SECONDS; "$@"; log "step '$1' took $((SECONDS - s)) s"; }
# shellcheck source=tests/vm/qemu.sh
. "$HERE/qemu.sh"

kernel_ready() {
  # packages, Debian's kernel and depmod: tests/vm/run.sh's own preparation (cached)
  CUBECAL_VM_WORK=$WORK bash "$HERE/run.sh" prepare || die "tests/vm/run.sh prepare failed"
  KVER=$(cat "$WORK/kver")
  local p missing=()
  for p in mmdebstrap e2fsprogs; do dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'ok installed' || missing+=("$p"); done
  if [ ${#missing[@]} -gt 0 ]; then
    log "installing: ${missing[*]}"
    apt-get update -qq || die "apt-get update failed"
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null || die "apt-get install failed"
  fi
}

# module_closure DIR MODULE... : the .ko paths (relative to DIR) of the modules and their dependencies
module_closure() {
  local md=$1 m line; shift
  for m in "$@"; do
    line=$(grep -E "/${m}\.ko(\.[a-z]+)?:" "$md/modules.dep") || die "module $m not in modules.dep"
    printf '%s\n' ${line%%:*} ${line#*:}
  done | sort -u
}

copy_modules() { # copy_modules DEST_ROOT MODULE...
  local dest=$1 md=$WORK/kernel-$KVER/root/lib/modules/$KVER f; shift
  for f in $(module_closure "$md" "$@"); do
    mkdir -p "$dest/lib/modules/$KVER/$(dirname "$f")"; cp "$md/$f" "$dest/lib/modules/$KVER/$f"
  done
  cp "$md"/modules.order "$md"/modules.builtin "$md"/modules.builtin.modinfo "$dest/lib/modules/$KVER/"
  depmod -b "$dest" "$KVER"
}

rootfs() {
  local R=$WORK/systemd-rootfs stamp
  # rebuilt when the suite, the packages, the kernel or this function change
  stamp=$( { printf '%s\n' "$SUITE" "$GUEST_PKGS" "$KVER"; declare -f rootfs copy_modules; } | sha256sum | cut -c1-16)
  if [ -d "$R" ] && [ "$(cat "$WORK/systemd-rootfs.stamp" 2>/dev/null)" = "$stamp" ]; then return 0; fi
  rm -rf "$R"
  log "mmdebstrap $SUITE ($GUEST_PKGS)"
  mmdebstrap --quiet --variant=essential --include="$GUEST_PKGS" \
    --dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-exclude=/usr/share/man/*' \
    --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-exclude=/usr/share/info/*' \
    "$SUITE" "$R" "$MIRROR" > "$WORK/mmdebstrap.log" 2>&1 || die "mmdebstrap failed (see $WORK/mmdebstrap.log)"
  copy_modules "$R" vivid 9p 9pnet_virtio virtio_pci
  echo cubecal-vm > "$R/etc/hostname"
  : > "$R/etc/fstab"
  # a quiet, quick boot: no login prompts, nothing waiting for a network
  ln -sf /dev/null "$R/etc/systemd/system/serial-getty@ttyS0.service"
  ln -sf /dev/null "$R/etc/systemd/system/getty@tty1.service"
  ln -sf /dev/null "$R/etc/systemd/system/systemd-timesyncd.service"
  # the test driver: a oneshot unit that runs the guest script from the 9p share, then powers off
  cat > "$R/etc/systemd/system/cubecal-vmtest.service" <<'UNIT'
[Unit]
Description=cubecal VM test driver (tests/vm/service-guest.sh)
After=multi-user.target
[Service]
Type=oneshot
ExecStart=/usr/local/sbin/cubecal-vmtest
StandardOutput=tty
StandardError=tty
TTYPath=/dev/ttyS0
TimeoutStartSec=infinity
[Install]
WantedBy=multi-user.target
UNIT
  mkdir -p "$R/etc/systemd/system/multi-user.target.wants"
  ln -sf /etc/systemd/system/cubecal-vmtest.service "$R/etc/systemd/system/multi-user.target.wants/"
  cat > "$R/usr/local/sbin/cubecal-vmtest" <<'DRIVER'
#!/bin/sh
T=$(sed -n 's/.*vmtest_timeout=\([0-9]*\).*/\1/p' /proc/cmdline)
( sleep "${T:-300}"; echo "VMTEST-EXIT: 124 (guest watchdog after ${T:-300}s)"; systemctl poweroff -ff ) &
echo "VMTEST: systemd guest up, uptime=$(cut -d' ' -f1 /proc/uptime)"
rc=1
mkdir -p /mnt/host
if modprobe 9pnet_virtio && modprobe 9p &&
   mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000 host0 /mnt/host; then
  if [ -x /mnt/host/service-guest.sh ]; then (cd /mnt/host && ./service-guest.sh); rc=$?; else echo "VMTEST: no service-guest.sh"; fi
else
  echo "VMTEST: host share not mounted"
fi
echo "VMTEST-EXIT: $rc uptime=$(cut -d' ' -f1 /proc/uptime)"
sync; umount /mnt/host 2>/dev/null
systemctl poweroff -ff
DRIVER
  chmod +x "$R/usr/local/sbin/cubecal-vmtest"
  echo "$stamp" > "$WORK/systemd-rootfs.stamp"
  log "root file system: $(du -sh "$R" | cut -f1)"
}

initramfs() {
  local R=$WORK/initramfs-systemd-root a stamp
  stamp=$(cat "$HERE/init-systemd.sh" | sha256sum | cut -c1-16)-$KVER
  if [ -s "$WORK/initramfs-systemd.gz" ] && [ "$(cat "$WORK/initramfs-systemd.stamp" 2>/dev/null)" = "$stamp" ]; then return 0; fi
  rm -rf "$R"; mkdir -p "$R"/{bin,sbin,proc,sys,dev,newroot}
  cp /bin/busybox "$R/bin/busybox"
  for a in $("$R/bin/busybox" --list); do [ "$a" = busybox ] || ln -sf busybox "$R/bin/$a"; done
  copy_modules "$R" virtio_pci virtio_blk ext4 crc32c_generic
  cp "$HERE/init-systemd.sh" "$R/init"; chmod +x "$R/init"
  (cd "$R" && find . | cpio -o -H newc --quiet | gzip -1) > "$WORK/initramfs-systemd.gz"
  echo "$stamp" > "$WORK/initramfs-systemd.stamp"
}

build() {
  local S=$WORK/service-share stage=$WORK/systemd-stage bin=${CUBECAL_VM_BIN:-$WORK/share/cubecal}
  if [ ! -x "$bin" ]; then
    log "no static cubecal at $bin: building it (tests/vm/run.sh build)"
    CUBECAL_VM_WORK=$WORK bash "$HERE/run.sh" build || die "static build failed"
  fi
  readelf -d "$bin" 2>/dev/null | grep -q NEEDED && die "$bin is not statically linked"
  rm -rf "$stage" "$S"; mkdir -p "$S/out"
  cp -a "$WORK/systemd-rootfs" "$stage"
  # the install path a user follows, into the guest's root
  DESTDIR=$stage bash "$ROOT/deploy/install.sh" --bin "$bin" > "$WORK/install.log" 2>&1 ||
    { cat "$WORK/install.log" >&2; die "deploy/install.sh failed"; }
  rm -f "$WORK/rootfs.img"
  mke2fs -q -t ext4 -L cubecal-root -d "$stage" "$WORK/rootfs.img" 1G || die "mke2fs -d failed"
  rm -rf "$stage"
  cp "$bin" "$S/cubecal"
  cp "$HERE/service-guest.sh" "$S/service-guest.sh"; chmod +x "$S/service-guest.sh"
  cp "$HERE/station.toml" "$S/station.toml"
}

boot() {
  [ -n "${KVER:-}" ] || KVER=$(cat "$WORK/kver")
  local s=$SECONDS rc
  rc=$(vm_boot "$WORK/service-guest.log" $((VM_TIMEOUT + 90)) 1024 "$WORK/initramfs-systemd.gz" \
    "systemd.show_status=false vmtest_timeout=$VM_TIMEOUT" "$WORK/service-share" \
    -drive file="$WORK/rootfs.img",if=virtio,format=raw,snapshot=on)
  log "guest finished: exit=${rc:-none} boot+test wall=$((SECONDS - s)) s (console: $WORK/service-guest.log)"
  grep -E '^(RESULT|STATUS|VMTEST|watchdog|unit)|profile\|' "$WORK/service-guest.log" | sed 's/^/  /' >&2 || true
  if [ "${rc:-x}" = 0 ]; then log "PASS"; return 0; fi
  log "FAIL — last 80 console lines:"; tail -80 "$WORK/service-guest.log" | sed 's/^/  | /' >&2
  return 1
}

case "${1:-all}" in
  rootfs) kernel_ready; timed rootfs; timed initramfs ;;
  build) KVER=$(cat "$WORK/kver"); timed build ;;
  boot) boot ;;
  all) kernel_ready; timed rootfs; timed initramfs; timed build; boot ;;
  *) echo "usage: $0 [all|rootfs|build|boot]" >&2; exit 2 ;;
esac
