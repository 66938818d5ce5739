#!/usr/bin/env bash
# Installs cubecal as an unattended calibration station: the binary, the systemd unit template
# cubecal@.service, the udev rules that start it when a camera is plugged in and name the turntable
# /dev/cubecal-turntable, an example /etc/cubecal/station.toml (never overwriting an existing one) and
# the README; then reloads systemd and udev. See README.md, "Run it as a service".
#
#   cargo build --release --locked && sudo bash deploy/install.sh [--bin PATH] [--trigger]
#
#   --bin PATH   the cubecal binary to install (default: target/release/cubecal)
#   --trigger    also replay "add" events for cameras already plugged in (starts the service on them)
#   DESTDIR=DIR  install into a staging root (an image, the VM test) instead of /: no reloads then
set -euo pipefail
cd "$(dirname "$0")/.."

bin="${CARGO_TARGET_DIR:-target}/release/cubecal"
trigger=0
while [ $# -gt 0 ]; do
  case "$1" in
    --bin) bin="${2:?--bin needs a path}"; shift 2 ;;
    --trigger) trigger=1; shift ;;
    -h|--help) sed -n '2,12p' "$0"; exit 0 ;;
    *) echo "install.sh: unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done
dest="${DESTDIR:-}"

[ -x "$bin" ] || { echo "install.sh: no executable $bin: build it first (cargo build --release --locked) or pass --bin PATH" >&2; exit 3; }
if [ -z "$dest" ] && [ "$(id -u)" -ne 0 ]; then
  echo "install.sh: run as root (sudo bash deploy/install.sh), or set DESTDIR to stage the files" >&2; exit 2
fi
config_src=fixtures/station.toml
[ -f "$config_src" ] || { echo "install.sh: missing $config_src (the example station configuration)" >&2; exit 3; }

install -D -m 0755 "$bin" "$dest/usr/local/bin/cubecal"
install -D -m 0644 deploy/systemd/cubecal@.service "$dest/etc/systemd/system/cubecal@.service"
install -D -m 0644 udev/99-cubecal.rules "$dest/etc/udev/rules.d/99-cubecal.rules"
install -D -m 0644 udev/99-cubecal-station.rules "$dest/etc/udev/rules.d/99-cubecal-station.rules"
install -D -m 0644 README.md "$dest/usr/local/share/doc/cubecal/README.md"
# The live page is off by default; its drop-in waits here (README "The live page").
install -D -m 0644 deploy/systemd/live-page.conf "$dest/usr/local/share/doc/cubecal/live-page.conf"
if [ -e "$dest/etc/cubecal/station.toml" ]; then
  echo "install.sh: keeping the existing /etc/cubecal/station.toml (example: $config_src)"
else
  install -D -m 0644 "$config_src" "$dest/etc/cubecal/station.toml"
  echo "install.sh: wrote /etc/cubecal/station.toml from $config_src: edit it for this station"
fi
echo "install.sh: installed /usr/local/bin/cubecal, /etc/systemd/system/cubecal@.service, /etc/udev/rules.d/99-cubecal{,-station}.rules${dest:+ under $dest}"

if [ -z "$dest" ]; then
  systemctl daemon-reload
  udevadm control --reload
  # The turntable's adapter may already be plugged in: give it its /dev/cubecal-turntable link now.
  udevadm trigger --action=change --subsystem-match=tty
  if [ "$trigger" = 1 ]; then
    udevadm trigger --action=add --subsystem-match=video4linux
  fi
  echo "install.sh: done. Plug in a camera, then: systemctl status 'cubecal@*' ; journalctl -u 'cubecal@*'"
fi
