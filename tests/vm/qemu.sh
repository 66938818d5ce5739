# tests/vm/qemu.sh — sourced by tests/vm/run.sh and tests/vm/service.sh: one boot of Debian's kernel
# under qemu (TCG unless ACCEL=kvm), serial console to a log, the host directory SHARE as 9p tag host0.
#
# vm_boot LOG LIMIT_S MEM_MB INITRD "KERNEL ARGS" SHARE [more qemu args...]
#   Needs WORK and KVER (the kernel in $WORK/kernel-$KVER). A host `timeout` of LIMIT_S bounds qemu
#   whatever the guest does. Prints the guest's VMTEST-EXIT code (nothing if it never printed one).
vm_boot() {
  local log=$1 limit=$2 mem=$3 initrd=$4 append=$5 share=$6 cpu=max
  shift 6
  [ "${ACCEL:-tcg}" = kvm ] && cpu=host
  rm -f "$log"
  timeout "$limit" qemu-system-x86_64 -machine pc,accel="${ACCEL:-tcg}" -cpu "$cpu" -smp 1 -m "$mem" \
    -kernel "$WORK/kernel-$KVER/boot-image" -initrd "$initrd" \
    -append "console=ttyS0 quiet loglevel=3 panic=-1 rdinit=/init $append" \
    -display none -no-reboot -nodefaults -serial stdio \
    -virtfs local,path="$share",mount_tag=host0,security_model=none,id=host0 \
    "$@" </dev/null 2>&1 | tr -d '\r' > "$log" || true
  sed -n 's/^VMTEST-EXIT: \([0-9]*\).*/\1/p' "$log" | tail -1
}
