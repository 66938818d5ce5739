#!/usr/bin/env python3
"""OpenCV's fisheye calibration (cv2.fisheye.calibrate) on given planar views, the peer of cubecal's
`--model kb4` in tests/fisheye.rs.

    fisheye_calibrate.py VIEWS.json

VIEWS.json: {"image_size": [w, h], "views": [{"xyz": [[x, y, 0], ...], "uv": [[u, v], ...]}, ...]}
with each view's points in its own plane's coordinates (z = 0): cv2.fisheye.calibrate initialises
each view's pose from a homography and takes no 3D rig. Flags: CALIB_RECOMPUTE_EXTRINSIC |
CALIB_FIX_SKEW (what its documentation recommends), 100 iterations or a 1e-12 step. Prints JSON:
{"version", "K": [fx, fy, cx, cy], "D": [k1, k2, k3, k4], "rms"} (rms: OpenCV's own figure, the
root mean square of the residual norms).
"""

import json
import sys

import cv2
import numpy as np


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    with open(sys.argv[1], encoding="utf-8") as f:
        spec = json.load(f)
    obj = [np.asarray(v["xyz"], dtype=np.float64).reshape(-1, 1, 3) for v in spec["views"]]
    img = [np.asarray(v["uv"], dtype=np.float64).reshape(-1, 1, 2) for v in spec["views"]]
    size = tuple(int(s) for s in spec["image_size"])
    flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rms, k, d, _, _ = cv2.fisheye.calibrate(obj, img, size, None, None, flags=flags, criteria=criteria)
    print(
        json.dumps(
            {
                "version": cv2.__version__,
                "K": [k[0, 0], k[1, 1], k[0, 2], k[1, 2]],
                "D": [float(x) for x in np.ravel(d)],
                "rms": rms,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
