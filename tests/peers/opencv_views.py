#!/usr/bin/env python3
"""Which views of the real chessboard sets OpenCV labels: findChessboardCornersSB (EXHAUSTIVE | ACCURACY)
and findChessboardCorners (ADAPTIVE_THRESH | NORMALIZE_IMAGE), per image. Writes the record that
tests/real_views_vs_opencv.rs holds cubecal to (fixtures/peers/opencv_views.json): no view either
detector labels may be lost by cubecal, except views it refutes with a printed reason.

usage: python3 tests/peers/opencv_views.py > fixtures/peers/opencv_views.json
(from the repository root, ../shared/datasets beside it; OpenCV's SB detector takes a few minutes
on the 1920 × 1080 photos)."""
import glob, json, os, sys
import cv2

cv2.setNumThreads(1)
ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..")
DATA = os.path.join(ROOT, "..", "shared", "datasets")
# (set, image glob under the set, inner corners cols x rows as OpenCV counts them)
SETS = [
    ("opencv_stereo_left_right", "images/left*.jpg", (9, 6)),
    ("opencv_stereo_left_right", "images/right*.jpg", (9, 6)),
    ("pose2sim_board_4x7", "images/*.jpg", (4, 7)),
    ("pycalib_chessboard_10x7", "images/*.jpg", (10, 7)),
]
out = {"opencv": cv2.__version__, "sets": []}
for name, pattern, size in SETS:
    views = []
    for path in sorted(glob.glob(os.path.join(DATA, name, pattern))):
        g = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        sb, _ = cv2.findChessboardCornersSB(g, size, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        classic, _ = cv2.findChessboardCorners(
            g, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        views.append({"image": os.path.relpath(path, os.path.join(DATA, name)), "sb": bool(sb),
                      "classic": bool(classic)})
        print(f"{name} {views[-1]}", file=sys.stderr)
    out["sets"].append({"set": name, "pattern": pattern, "inner_corners": list(size), "views": views})
json.dump(out, sys.stdout, indent=1)
print()
