#!/usr/bin/env bash
# Compare OpenCV's chessboard detectors (and cubecal's, once `cubecal detect` exists) with the exact
# ground truth of two sets of cubecal renders. See tests/peers/README.md. Run from anywhere:
#
#   N_FRAMES=24 bash tests/peers/compare.sh
#
# Environment: N_FRAMES (frames per set, default 24), PEERS_DIR (work directory, default
# target/peers under the repository), CARGO_TARGET_DIR (where cargo builds), CARGO_JOBS (default 1),
# OPENCV_PKG / NUMPY_PKG (pip requirement strings; pinned by default so that runs are comparable).
# Not part of `cargo test` or CI: it needs PyPI.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
cd "$repo"
peers=${PEERS_DIR:-target/peers}
n_frames=${N_FRAMES:-24}
jobs=${CARGO_JOBS:-1}
opencv_pkg=${OPENCV_PKG:-opencv-python-headless==5.0.0.93}
numpy_pkg=${NUMPY_PKG:-numpy==2.4.6}
rig=fixtures/rigs/cube_outside.toml
bin="${CARGO_TARGET_DIR:-target}/release/cubecal"
venv="$peers/venv"
mkdir -p "$peers"

step_start=$SECONDS
step() { # end the previous step (print its time) and announce the next
    if [[ -n ${step_name:-} ]]; then
        echo "== $step_name: $((SECONDS - step_start)) s" >&2
    fi
    step_name=$1
    step_start=$SECONDS
    [[ -n $1 ]] && echo "== $1 ..." >&2
    return 0
}

step "python venv ($opencv_pkg, $numpy_pkg)"
if ! python3 -c 'import venv, ensurepip' 2>/dev/null; then
    echo "python3 has no venv/ensurepip: installing python3-venv" >&2
    apt-get update -qq && apt-get install -y -qq python3-venv >&2
fi
if [[ ! -x $venv/bin/python ]]; then
    python3 -m venv "$venv"
fi
# Idempotent: with pinned versions already installed pip changes nothing and asks no index.
"$venv/bin/pip" install -q --disable-pip-version-check "$numpy_pkg" "$opencv_pkg" >&2
"$venv/bin/python" -c 'import cv2, numpy; print("OpenCV", cv2.__version__, "numpy", numpy.__version__)' >&2

step "cargo build --release --bin cubecal"
cargo build --release --locked -j "$jobs" --bin cubecal

have_detect=0
if "$bin" detect --help >/dev/null 2>&1; then
    have_detect=1
else
    echo "cubecal has no 'detect' subcommand yet: comparing OpenCV only" >&2
fi

# name, then the render options of that set
render_set() {
    local name=$1
    shift
    local dir="$peers/$name"
    step "render $name ($n_frames frames)"
    rm -rf "$dir"
    "$bin" render "$rig" --out "$dir" --poses "random:$n_frames" "$@" >"$peers/$name.render.txt"
}

render_set realistic --width 1920 --height 1080 --fx 1400 --fy 1400 --k1 -0.1 \
    --blur 1.0 --noise 2 --gamma 2.2 --vignetting 0.3 --seed 1
render_set hard --width 1280 --height 960 --fx 700 --fy 700 --k1 -0.3 \
    --blur 1.5 --noise 5 --gamma 2.2 --vignetting 0.3 --black 0.3 --white 0.55 --seed 2

for name in realistic hard; do
    dir="$peers/$name"
    cubecal_args=()
    if [[ $have_detect == 1 ]]; then
        step "cubecal detect on $name"
        status=0
        "$bin" detect --rig "$rig" --json "$dir"/frame_*.png >"$peers/$name.cubecal.json" || status=$?
        if [[ -s $peers/$name.cubecal.json ]]; then
            [[ $status == 0 ]] || echo "cubecal detect exited $status on $name; using its output" >&2
            cubecal_args=(--cubecal-json "$peers/$name.cubecal.json")
        else
            echo "cubecal detect exited $status with no output on $name: skipping cubecal" >&2
        fi
    fi
    step "self-check of the metric code on $name"
    "$venv/bin/python" tests/peers/opencv_compare.py --frames "$dir" --self-check
    step "OpenCV on $name"
    "$venv/bin/python" tests/peers/opencv_compare.py --frames "$dir" --title "$name" \
        --max-angle 75 --json "$peers/$name.json" \
        --save-masked "$peers/masked/$name" --save-masked-count 3 \
        "${cubecal_args[@]}" | tee "$peers/$name.txt"
done
step ""
echo "tables: $peers/realistic.txt $peers/hard.txt; per-face records: $peers/*.json" >&2
