#!/bin/bash
# tests/vm/run.sh — run cubecal's V4L2 capture layer against a REAL kernel driver (vivid) in a qemu guest.
#
# The build machines have no camera and cannot load kernel modules, but they can boot Debian's own
# kernel under qemu (TCG) with the `vivid` virtual video driver. This script:
#   1. installs the host packages it needs (idempotent; `apt-get update` first, only when something is missing),
#   2. downloads and unpacks the Debian kernel .deb (cached per kernel version, nothing installed on the host),
#   3. builds an initramfs with busybox + the vivid and 9p module closures (cached, rebuilt when /init changes),
#   4. builds STATIC executables of the project (`cubecal` and the `capture_vivid` integration test,
#      `+crt-static` for x86_64-unknown-linux-gnu),
#   5. boots the guest, which loads vivid and runs tests/vm/guest.sh from a 9p share, bounded by a guest
#      watchdog and a host `timeout`,
#   6. prints the guest's RESULT lines and exits 0 on PASS, 1 on FAIL (2 on a harness/setup error).
#
# usage: tests/vm/run.sh [all|prepare|build|boot]     (default: all)
# env:   CUBECAL_VM_WORK (default $CARGO_TARGET_DIR/vm or ./target/vm)  scratch + cache directory
#        KVER (default: whatever linux-image-amd64 depends on)  VM_TIMEOUT=300 (guest watchdog, s)
#        ACCEL=tcg (kvm only on hosts with real hardware KVM)
# Background and measurements: /work/shared/reference/v4l2-vm/README.md (vivid loop, pitfalls).
set -euo pipefail
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
ROOT=$(cd "$HERE/../.." && pwd)
TARGET_DIR=${CARGO_TARGET_DIR:-$ROOT/target}
WORK=${CUBECAL_VM_WORK:-$TARGET_DIR/vm}
ACCEL=${ACCEL:-tcg}
VM_TIMEOUT=${VM_TIMEOUT:-300}
RUST_TARGET=x86_64-unknown-linux-gnu
export DEBIAN_FRONTEND=noninteractive
mkdir -p "$WORK"
T0=$SECONDS
log() { echo "[vm-test +$((SECONDS - T0))s] $*" >&2; }
die() { log "SETUP ERROR: $*"; exit 2; }
timed() { local s=$SECONDS; "$@"; log "step '$1' took $((SECONDS - s)) s"; }
# shellcheck source=tests/vm/qemu.sh
. "$HERE/qemu.sh"

PKGS="qemu-system-x86 busybox-static cpio kmod xz-utils libclang-dev libc6-dev"

packages() {
  local missing=() p
  for p in $PKGS; do dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'ok installed' || missing+=("$p"); done
  if [ ${#missing[@]} -gt 0 ]; then
    log "installing: ${missing[*]}"
    apt-get update -qq || die "apt-get update failed"
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null || die "apt-get install failed"
  fi
  if [ -z "${KVER:-}" ]; then
    KVER=$(apt-cache depends linux-image-amd64 2>/dev/null | sed -n 's/.*Depends: linux-image-\(.*\)$/\1/p' | head -1)
    if [ -z "$KVER" ]; then apt-get update -qq || true
      KVER=$(apt-cache depends linux-image-amd64 | sed -n 's/.*Depends: linux-image-\(.*\)$/\1/p' | head -1); fi
  fi
  [ -n "$KVER" ] || die "cannot resolve the kernel version (linux-image-amd64)"
  echo "$KVER" > "$WORK/kver"
  log "guest kernel: linux-image-$KVER"
}

kernel() {
  local K=$WORK/kernel-$KVER
  if [ -s "$K/boot-image" ]; then return 0; fi
  rm -rf "$K"; mkdir -p "$K/debs" "$K/root"
  (cd "$K/debs" && apt-get download -q "linux-image-$KVER" 2>&1 | grep -v unsandboxed || true)
  ls "$K"/debs/linux-image-"$KVER"_*.deb >/dev/null 2>&1 || die "could not download linux-image-$KVER"
  dpkg -x "$K"/debs/linux-image-"$KVER"_*.deb "$K/root"
  depmod -b "$K/root" "$KVER"   # the .deb ships no modules.dep (postinst normally makes it)
  # qemu boots the uncompressed ELF vmlinux (PVH entry) ~3 s faster under TCG than the bzImage.
  local vz=$K/root/boot/vmlinuz-$KVER off
  off=$(LC_ALL=C grep -aobUP '\xfd7zXZ\x00' "$vz" | head -1 | cut -d: -f1 || true)
  if [ -n "$off" ] && tail -c +$((off + 1)) "$vz" > "$K/vmlinux.xz" &&
     xz -dc --single-stream < "$K/vmlinux.xz" > "$K/vmlinux" 2>/dev/null; then
    ln -sf vmlinux "$K/boot-image"
  else
    log "no vmlinux extracted; booting the bzImage"; ln -sf "root/boot/vmlinuz-$KVER" "$K/boot-image"
  fi
  rm -f "$K/vmlinux.xz" "$K"/debs/*.deb
}

initramfs() {
  local K=$WORK/kernel-$KVER R=$WORK/initramfs-root MD=$WORK/kernel-$KVER/root/lib/modules/$KVER
  local stamp; stamp=$(cat "$HERE/init.sh" "$0" | sha256sum | cut -c1-16)-$KVER
  if [ -s "$WORK/initramfs.gz" ] && [ "$(cat "$WORK/initramfs.stamp" 2>/dev/null)" = "$stamp" ]; then return 0; fi
  rm -rf "$R"; mkdir -p "$R"/{bin,sbin,proc,sys,dev,tmp,mnt/host,etc,lib/modules/$KVER}
  cp /bin/busybox "$R/bin/busybox"
  # pitfall: `busybox --list` contains "busybox" itself; linking it onto itself gives ELOOP at init
  for a in $("$R/bin/busybox" --list); do [ "$a" = busybox ] || ln -sf busybox "$R/bin/$a"; done
  local files=() m line f
  for m in vivid virtio_pci 9pnet_virtio 9p; do
    line=$(grep -E "/${m}\.ko(\.[a-z]+)?:" "$MD/modules.dep") || die "module $m not in modules.dep"
    # shellcheck disable=SC2206
    files+=(${line%%:*} ${line#*:})
  done
  for f in $(printf '%s\n' "${files[@]}" | sort -u); do
    mkdir -p "$R/lib/modules/$KVER/$(dirname "$f")"; cp "$MD/$f" "$R/lib/modules/$KVER/$f"
  done
  cp "$MD"/modules.order "$MD"/modules.builtin "$MD"/modules.builtin.modinfo "$R/lib/modules/$KVER/"
  depmod -b "$R" "$KVER"
  cp "$HERE/init.sh" "$R/init"; chmod +x "$R/init"
  (cd "$R" && find . | cpio -o -H newc --quiet | gzip -1) > "$WORK/initramfs.gz"
  echo "$stamp" > "$WORK/initramfs.stamp"
  log "initramfs: $(du -h "$WORK/initramfs.gz" | cut -f1)"
}

build() {
  local S=$WORK/share exe
  rm -rf "$S"; mkdir -p "$S"
  # explicit --target keeps +crt-static away from build scripts (bindgen runs in v4l2-sys-mit's build.rs)
  export RUSTFLAGS="-C target-feature=+crt-static"
  # one build gives both executables: integration tests build the `cubecal` binary too (same profile)
  (cd "$ROOT" && cargo test -q --locked --no-run --message-format=json --target "$RUST_TARGET" \
    --profile vmtest --test capture_vivid) > "$WORK/build.json" || die "cargo test --no-run failed"
  exe=$(grep '"name":"cubecal"' "$WORK/build.json" | grep '"kind":\["bin"\]' |
    sed -n 's/.*"executable":"\([^"]*\)".*/\1/p' | tail -1)
  [ -n "$exe" ] || die "no cubecal executable in the build output"
  cp "$exe" "$S/cubecal"
  exe=$(grep '"name":"capture_vivid"' "$WORK/build.json" | sed -n 's/.*"executable":"\([^"]*\)".*/\1/p' | tail -1)
  [ -n "$exe" ] || die "cargo test --no-run produced no executable"
  cp "$exe" "$S/capture_vivid"
  for exe in "$S/cubecal" "$S/capture_vivid"; do
    if readelf -d "$exe" 2>/dev/null | grep -q NEEDED; then die "$exe is not statically linked"; fi
  done
  # a rendered rig with ground truth for the loop test, made on the host by the same (static) binary,
  # at the size of vivid's HDMI loop
  mkdir -p "$S/render"
  "$S/cubecal" render "$ROOT/fixtures/rigs/cube_outside.toml" --out "$S/render" --width 1280 --height 720 \
    --blur 0.8 --noise 1 --seed 3 > "$WORK/render.log" 2>&1 || die "cubecal render failed (see $WORK/render.log)"
  cp "$ROOT/fixtures/rigs/cube_outside.toml" "$S/render/rig.toml"
  cp "$HERE/guest.sh" "$S/run.sh"; chmod +x "$S/run.sh"
}

boot() {
  [ -n "${KVER:-}" ] || KVER=$(cat "$WORK/kver" 2>/dev/null) || die "run 'prepare' first"
  local s=$SECONDS rc
  [ -x "$WORK/share/run.sh" ] || die "run 'build' first"
  # host-side watchdog as well as the guest's own: qemu can never hang CI
  rc=$(vm_boot "$WORK/guest.log" $((VM_TIMEOUT + 60)) 768 "$WORK/initramfs.gz" \
    "vmtest_timeout=$VM_TIMEOUT" "$WORK/share")
  log "guest finished: exit=${rc:-none} boot+test wall=$((SECONDS - s)) s (full console: $WORK/guest.log)"
  grep -E '^(RESULT|test |VMTEST)' "$WORK/guest.log" | sed 's/^/  /' >&2 || true
  if [ "${rc:-x}" = 0 ]; then log "PASS"; return 0; fi
  log "FAIL — last 60 console lines:"; tail -60 "$WORK/guest.log" | sed 's/^/  | /' >&2
  return 1
}

prepare() { timed packages; timed kernel; timed initramfs; }
case "${1:-all}" in
  prepare) prepare ;;
  build) timed build ;;
  boot) boot ;;
  all) prepare; timed build; boot ;;
  *) echo "usage: $0 [all|prepare|build|boot]" >&2; exit 2 ;;
esac
