#!/usr/bin/env python3
"""Load cubecal's exports with the real tools and project points with them.

Usage: project.py DIR
DIR holds points.json ({"points": [[X, Y, Z], ...]} in the camera frame), opencv.yaml, ros.yaml and
model.cameramodel, written by tests/profile.rs. Prints one JSON object on stdout:
{"opencv": [[u, v], ...], "ros": [...], "mrcal": [...], "loaded": {...}} with what each tool read, so the
Rust test can compare the pixels with cubecal's own projection (the comparison and its tolerance live
there). Exit 2 when a tool is missing (the message names it), 1 on any other failure.

- OpenCV: cv2.FileStorage reads camera_matrix / distortion_coefficients; cv2.projectPoints projects.
- ROS: camera_calibration_parsers.readCalibration (ROS's own C++ parser behind a Python wrapper) reads
  the camera_info YAML into a sensor_msgs/CameraInfo; its K and D are projected with cv2.projectPoints,
  which is what ROS's image_geometry does.
- mrcal: mrcal.cameramodel reads the .cameramodel; mrcal.project projects with mrcal's own lens models.
"""
import json
import os
import sys

try:
    import numpy as np
    import cv2
    import mrcal
    import camera_calibration_parsers
except ImportError as e:  # pragma: no cover - reported to the Rust test
    print(f"missing tool: {e}", file=sys.stderr)
    sys.exit(2)


def main():
    d = sys.argv[1]
    with open(os.path.join(d, "points.json")) as f:
        pts = np.array(json.load(f)["points"], dtype=np.float64).reshape(-1, 1, 3)
    zero = np.zeros(3, dtype=np.float64)
    out = {"loaded": {}}

    fs = cv2.FileStorage(os.path.join(d, "opencv.yaml"), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise SystemExit("cv2.FileStorage could not open opencv.yaml")
    k = fs.getNode("camera_matrix").mat()
    dist = fs.getNode("distortion_coefficients").mat()
    w = int(fs.getNode("image_width").real())
    h = int(fs.getNode("image_height").real())
    fs.release()
    if k is None or dist is None:
        raise SystemExit("opencv.yaml: camera_matrix or distortion_coefficients missing")
    uv, _ = cv2.projectPoints(pts, zero, zero, k, dist)
    out["opencv"] = uv.reshape(-1, 2).tolist()
    out["loaded"]["opencv"] = {"K": k.tolist(), "D": dist.ravel().tolist(), "size": [w, h]}

    res = camera_calibration_parsers.readCalibration(os.path.join(d, "ros.yaml"))
    if res is None:
        raise SystemExit("camera_calibration_parsers.readCalibration rejected ros.yaml")
    name, info = res
    k = np.array(info.K, dtype=np.float64).reshape(3, 3)
    dist = np.array(info.D, dtype=np.float64)
    uv, _ = cv2.projectPoints(pts, zero, zero, k, dist)
    out["ros"] = uv.reshape(-1, 2).tolist()
    out["loaded"]["ros"] = {"name": name, "K": k.tolist(), "D": dist.tolist(),
                            "model": info.distortion_model, "size": [info.width, info.height],
                            "P": list(info.P), "R": list(info.R)}

    m = mrcal.cameramodel(os.path.join(d, "model.cameramodel"))
    lensmodel, intrinsics = m.intrinsics()
    uv = mrcal.project(pts.reshape(-1, 3), lensmodel, intrinsics)
    out["mrcal"] = np.asarray(uv).reshape(-1, 2).tolist()
    out["loaded"]["mrcal"] = {"lensmodel": lensmodel, "intrinsics": list(map(float, intrinsics)),
                              "size": [int(x) for x in m.imagersize()]}

    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
