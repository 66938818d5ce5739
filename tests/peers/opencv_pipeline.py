"""OpenCV's bare calibration pipeline on a folder of photos of a plain chessboard, as an OpenCV user
runs it: imread (grey) + findChessboardCorners + cornerSubPix + calibrateCamera. The peer that
`cubecal calibrate --images` is timed against (issue 36; whole process against whole process).

usage: python3 opencv_pipeline.py [--board COLSxROWS] [--square MM] [--pattern GLOB] FOLDER
prints the views found, the RMS and K (one line each), so a timed run can be checked for the answer."""
import argparse
import glob
import os
import sys

import cv2
import numpy as np

ap = argparse.ArgumentParser()
ap.add_argument("folder")
ap.add_argument("--board", default="9x6", help="inner corners, OpenCV's convention")
ap.add_argument("--square", type=float, default=30.0, help="square size in mm")
ap.add_argument("--pattern", default="left*.jpg")
a = ap.parse_args()
cols, rows = (int(x) for x in a.board.split("x"))
paths = sorted(glob.glob(os.path.join(a.folder, a.pattern)))
if not paths:
    sys.exit(f"{a.folder}: no files match {a.pattern}")
obj = np.array([[c * a.square, r * a.square, 0] for r in range(rows) for c in range(cols)], np.float32)
crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
O, I, size = [], [], None
for p in paths:
    g = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
    if g is None:
        print(f"{p}: cannot read", file=sys.stderr)
        continue
    size = g.shape[::-1]
    ok, c = cv2.findChessboardCorners(g, (cols, rows))
    if not ok:
        continue
    c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), crit)
    O.append(obj)
    I.append(c)
rms, K, dist, _, _ = cv2.calibrateCamera(O, I, size, None, None)
print(f"views {len(O)}/{len(paths)}")
print(f"rms {rms:.4f}")
print(f"fx {K[0, 0]:.3f} fy {K[1, 1]:.3f} cx {K[0, 2]:.3f} cy {K[1, 2]:.3f}")
