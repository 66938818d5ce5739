#!/usr/bin/env bash
# tests/report_chromium.sh — open the demo run's report and a stored profile's report in headless
# Chromium (Debian's `chromium`) and check that every image decoded, every plot is there and nothing
# was logged to the console.
#
# 1. installs chromium when missing (apt; `apt-get update` first),
# 2. builds the demo run (12 poses, 1280×960), a poor-coverage run and a profile store with a
#    five-version camera, with their reports, through the ignored test `write_demo_runs` of
#    tests/report.rs,
# 3. loads a copy of each report with a small checker script prepended: it records resource and
#    script errors (capture phase, so a broken <img> counts) and on `load` writes into the DOM how many
#    images there are, how many failed to decode (naturalWidth 0) and how many inline SVG plots,
# 4. dumps the DOM with --dump-dom and requires `broken=0 errors=0`, 13 images (one per frame) and
#    6 plots for the demo, 3 plots (distortion, uncertainty, history) and no image for the profile;
#    any `CONSOLE` line Chromium logs is a failure too.
# With REPORT_SHOTS=DIR it also saves full-page screenshots of the reports there.
#
# exit 0 PASS, 1 FAIL, 2 setup error.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
die() { echo "report_chromium: SETUP ERROR: $*" >&2; exit 2; }

if ! command -v chromium >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq || die "apt-get update failed"
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq chromium >/dev/null || die "cannot install chromium"
fi
CHROMIUM=$(command -v chromium)

WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
CUBECAL_REPORT_DEMO_DIR="$WORK" cargo test --locked --test report -- --ignored --exact write_demo_runs \
  || die "building the demo runs failed"

chrome() {
  timeout 120 "$CHROMIUM" --headless --no-sandbox --disable-gpu --disable-dev-shm-usage \
    --no-first-run --hide-scrollbars --enable-logging=stderr --v=0 "$@"
}

CHECKER='<script>
(function () {
  var errors = [];
  window.addEventListener("error", function (e) {
    errors.push((e.target && e.target.tagName) || e.message || "error");
  }, true);
  window.addEventListener("load", function () {
    var imgs = Array.prototype.slice.call(document.images);
    var broken = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); }).length;
    var svgs = document.querySelectorAll("figure > svg").length;
    document.documentElement.setAttribute("data-check",
      "images=" + imgs.length + " broken=" + broken + " svgs=" + svgs + " errors=" + errors.length);
  });
})();
</script>'

fail=0
check() { # run_dir expected_images expected_svgs
  local run=$1 want_img=$2 want_svg=$3 name
  name=$(basename "$run")
  [ -f "$run/report.html" ] || { echo "FAIL $name: no report.html"; fail=1; return; }
  { printf '%s\n' "$CHECKER"; cat "$run/report.html"; } > "$run/report_checked.html"
  chrome --virtual-time-budget=10000 --dump-dom "file://$run/report_checked.html" \
    > "$WORK/$name.dom" 2> "$WORK/$name.log" || { echo "FAIL $name: chromium exited $?"; cat "$WORK/$name.log"; fail=1; return; }
  local got
  got=$(grep -o 'data-check="[^"]*"' "$WORK/$name.dom" || true)
  local want="data-check=\"images=$want_img broken=0 svgs=$want_svg errors=0\""
  if [ "$got" != "$want" ]; then
    echo "FAIL $name: got ${got:-no check result}, want $want"; fail=1
  else
    echo "ok   $name: $got"
  fi
  if grep -q 'CONSOLE' "$WORK/$name.log"; then
    echo "FAIL $name: console messages:"; grep 'CONSOLE' "$WORK/$name.log"; fail=1
  fi
  if [ -n "${REPORT_SHOTS:-}" ]; then
    mkdir -p "$REPORT_SHOTS"
    chrome --window-size=1500,${SHOT_HEIGHT:-7000} --screenshot="$REPORT_SHOTS/$name.png" \
      "file://$run/report.html" 2>/dev/null >/dev/null || true
  fi
}
# demo: 12 accepted poses + 1 frame that misses the rig (13 thumbnails), 6 plots
check "$WORK/demo" 13 6
# poor coverage: 6 poses, all accepted
check "$WORK/poor_coverage" 6 6
# profile: plots only (inline SVG), no <img>
check "$WORK/profile" 0 3
if [ "$fail" -ne 0 ]; then echo "report_chromium: FAIL"; exit 1; fi
echo "report_chromium: PASS"
