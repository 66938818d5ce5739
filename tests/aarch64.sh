#!/usr/bin/env bash
# tests/aarch64.sh — cubecal for a small ARM station computer (issue 36 line 3): cross-compiles the
# crate for aarch64-unknown-linux-gnu with Debian's cross toolchain, runs the library's unit tests
# (`--lib`) under qemu-user, and runs the detect and solve benches there, printing their figures.
#
#   1. installs gcc-aarch64-linux-gnu, libc6-dev-arm64-cross (with the arm64 kernel headers the v4l
#      crate's bindgen reads) and qemu-user, and the rustup target (idempotent, quiet when present);
#   2. `cargo test --release --lib` and `cargo bench --bench detect --bench solve` for the target, each
#      executable run by `qemu-aarch64 -L /usr/aarch64-linux-gnu` (cargo's target runner);
#   3. exits non-zero when the build, a unit test or a bench fails.
#
# One optimised build serves both steps (the release and bench profiles build the dependencies alike),
# in its own target directory (CUBECAL_AARCH64_TARGET_DIR, default $CARGO_TARGET_DIR/aarch64 or
# ./target/aarch64) so it never invalidates the host build. Unoptimised code is far too slow under
# qemu's instruction translation, hence `--release` for the unit tests too.
#
# The benches run 9 repetitions per figure (CUBECAL_BENCH_REPS; a cube frame takes ~0.5 s emulated,
# 25-50x native); under qemu-user the figures measure the emulator on this machine as much as the
# code: compare them with each other (noise / cube), not with a real board. Times of each step are
# printed (`[aarch64 +Ns]`).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
TRIPLE=aarch64-unknown-linux-gnu
SYSROOT=/usr/aarch64-linux-gnu
T0=$SECONDS
log() { echo "[aarch64 +$((SECONDS - T0))s] $*" >&2; }

packages=(gcc-aarch64-linux-gnu libc6-dev-arm64-cross qemu-user)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ "${#missing[@]}" -gt 0 ]; then
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  log "installing ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi
rustup target list --installed | grep -qx "$TRIPLE" || rustup target add "$TRIPLE"

export CARGO_TARGET_DIR="${CUBECAL_AARCH64_TARGET_DIR:-${CARGO_TARGET_DIR:-$ROOT/target}/aarch64}"
export CARGO_INCREMENTAL=0
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER="qemu-aarch64 -L $SYSROOT"
# bindgen (v4l-sys) must read the target's kernel and libc headers, not the host's.
export BINDGEN_EXTRA_CLANG_ARGS_aarch64_unknown_linux_gnu="--sysroot=$SYSROOT"
export CC_aarch64_unknown_linux_gnu=aarch64-linux-gnu-gcc

log "build (release, $TRIPLE) into $CARGO_TARGET_DIR"
cargo test --locked --release --target "$TRIPLE" --lib --benches --no-run
log "unit tests under qemu-aarch64"
cargo test --locked --release --target "$TRIPLE" --lib
log "detect and solve benches under qemu-aarch64 (CUBECAL_BENCH_REPS=${CUBECAL_BENCH_REPS:=9} repetitions)"
CUBECAL_BENCH_REPS=$CUBECAL_BENCH_REPS cargo bench --locked --target "$TRIPLE" --bench detect --bench solve
log "done"
