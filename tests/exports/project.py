#!/usr/bin/env python3
"""Load cubecal's exports with the real tools and project points with them.

Usage: project.py DIR
DIR holds points.json ({"points": [[X, Y, Z], ...]} in the camera frame), opencv.yaml and ros.yaml, and
model.cameramodel and kalibr.yaml when the profile has them, written by tests/profile.rs. Prints one
JSON object on stdout: {"opencv": [[u, v] or null, ...], "ros": [...], "mrcal": [...], "kalibr": [...],
"opencv_theta": [...], "loaded": {...}} with what each tool read, so the Rust test can compare the pixels
with cubecal's own projection (the comparison and its tolerance live there). A point a tool cannot
project is null (see the fisheye below); a file that is absent gives null for its tool. Exit 2 when a
tool is missing (the message names it), 1 on any other failure.

- OpenCV: cv2.FileStorage reads camera_matrix / distortion_coefficients (and fisheye_model, the flag
  OpenCV's calibration tutorial writes); cv2.projectPoints projects, or cv2.fisheye.projectPoints when
  fisheye_model is 1. cv::fisheye divides by Z before it takes the angle, so it projects a point behind
  the camera (Z <= 0) as its reflection through the centre: those points are null in "opencv" and their
  raw cv2.fisheye result is in "opencv_behind". "opencv_theta" is cv::fisheye's documented formula
  evaluated on the angle itself, θ = atan2(√(X² + Y²), Z), with the K and D cv2.FileStorage loaded: what
  the file's numbers mean past 90°, where cv2.fisheye cannot go.
- ROS: camera_calibration_parsers.readCalibration (ROS's own C++ parser behind a Python wrapper) reads
  the camera_info YAML into a sensor_msgs/CameraInfo; its K and D are projected with cv2.projectPoints,
  or cv2.fisheye.projectPoints for distortion_model equidistant, as ROS's image_geometry does.
- mrcal: mrcal.cameramodel reads the .cameramodel; mrcal.project projects with mrcal's own lens models.
- Kalibr cannot be installed here (it is a ROS workspace), so kalibr.yaml is read with yaml.safe_load, as
  Kalibr's ConfigReader reads it, and checked with that reader's rules (kalibr_check below, after
  ethz-asl/kalibr 1f60227, aslam_offline_calibration/kalibr/python/kalibr_common/ConfigReader.py); its
  points are projected with aslam_cv's pinhole projection and its radtan / equidistant distortion
  (aslam_cv/aslam_cameras/include/aslam/cameras/implementation/*Distortion.hpp) written out below, for
  Z > 0 as aslam_cv's PinholeProjection accepts.
"""
import json
import math
import os
import sys

try:
    import numpy as np
    import cv2
    import mrcal
    import camera_calibration_parsers
    import yaml
except ImportError as e:  # pragma: no cover - reported to the Rust test
    print(f"missing tool: {e}", file=sys.stderr)
    sys.exit(2)


def fisheye_in_front(pts, k, dist):
    """cv2.fisheye.projectPoints for the points with Z > 0; null for the others."""
    zero = np.zeros(3, dtype=np.float64)
    front = pts[:, 0, 2] > 0
    out = [None] * len(pts)
    if front.any():
        uv, _ = cv2.fisheye.projectPoints(pts[front], zero, zero, k, dist)
        for i, p in zip(np.flatnonzero(front), uv.reshape(-1, 2).tolist()):
            out[i] = p
    behind = [None] * len(pts)
    if (~front).any():
        uv, _ = cv2.fisheye.projectPoints(pts[~front], zero, zero, k, dist)
        for i, p in zip(np.flatnonzero(~front), uv.reshape(-1, 2).tolist()):
            behind[i] = p
    return out, behind


def project_opencv(pts, k, dist, fisheye):
    zero = np.zeros(3, dtype=np.float64)
    if fisheye:
        return fisheye_in_front(pts, k, dist)
    uv, _ = cv2.projectPoints(pts, zero, zero, k, dist)
    return uv.reshape(-1, 2).tolist(), None


def opencv_theta(pts, k, dist):
    """cv::fisheye's formula, θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), on the angle itself."""
    k1, k2, k3, k4 = dist.ravel().tolist()
    out = []
    for x, y, z in pts.reshape(-1, 3).tolist():
        rho = math.hypot(x, y)
        th = math.atan2(rho, z)
        t2 = th * th
        td = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        s = td / rho if rho > 0 else 0.0
        xd, yd = x * s, y * s
        out.append([k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]])
    return out


def kalibr_check(data):
    """Kalibr's ConfigReader rules for a camera chain; raises SystemExit naming the broken rule."""
    def fail(msg):
        raise SystemExit(f"kalibr.yaml: {msg}")

    def field(cam, name, key):
        if key not in cam:  # ConfigReader's catch_keyerror: "Field ... missing in file"
            fail(f"{name}: field {key} missing")
        return cam[key]

    if not isinstance(data, dict) or not data:
        fail("not a mapping of cameras")
    # CameraChainParameters.numCameras() is len(data): every top-level key must be a camera, cam0..camN-1
    if sorted(data) != [f"cam{i}" for i in range(len(data))]:
        fail(f"top-level keys {sorted(data)} are not cam0..cam{len(data) - 1}")
    for name, cam in data.items():
        model, intr = field(cam, name, "camera_model"), field(cam, name, "intrinsics")
        if model not in ("pinhole", "omni", "eucm", "ds"):
            fail(f"{name}: unknown camera model {model!r}")
        if model != "pinhole" or len(intr) != 4:  # the only model cubecal writes
            fail(f"{name}: expected pinhole with [fu, fv, pu, pv], got {model} {intr}")
        if not all(isinstance(v, float) and v >= 0.0 for v in intr):
            fail(f"{name}: focal length and principal point must be floats >= 0: {intr}")
        counts = {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}
        dm, dc = field(cam, name, "distortion_model"), field(cam, name, "distortion_coeffs")
        if dm not in counts or len(dc) != counts[dm]:
            fail(f"{name}: distortion model {dm!r} with {len(dc)} coefficients")
        res = field(cam, name, "resolution")
        if len(res) != 2 or not all(isinstance(v, int) for v in res):
            fail(f"{name}: invalid resolution {res}")
        if not isinstance(field(cam, name, "rostopic"), str):
            fail(f"{name}: rostopic has to be a string")
        if name != "cam0" and "T_cn_cnm1" not in cam:
            fail(f"{name}: T_cn_cnm1 missing")


def kalibr_project(cam, pts):
    """aslam_cv's PinholeProjection::euclideanToKeypoint with its distortion; null where Z <= 0."""
    fu, fv, pu, pv = cam["intrinsics"]
    dm, d = cam["distortion_model"], cam["distortion_coeffs"]
    out = []
    for X, Y, Z in pts.reshape(-1, 3).tolist():
        if Z <= 0:
            out.append(None)
            continue
        x, y = X / Z, Y / Z
        if dm == "radtan":
            k1, k2, p1, p2 = d
            mx2, my2, mxy = x * x, y * y, x * y
            rho2 = mx2 + my2
            rad = k1 * rho2 + k2 * rho2 * rho2
            x, y = (x + x * rad + 2.0 * p1 * mxy + p2 * (rho2 + 2.0 * mx2),
                    y + y * rad + 2.0 * p2 * mxy + p1 * (rho2 + 2.0 * my2))
        elif dm == "equidistant":
            k1, k2, k3, k4 = d
            r = math.sqrt(x * x + y * y)
            th = math.atan(r)
            t2 = th * th
            t4 = t2 * t2
            td = th * (1 + k1 * t2 + k2 * t4 + k3 * t4 * t2 + k4 * t4 * t4)
            s = td / r if r > 1e-8 else 1.0
            x, y = x * s, y * s
        elif dm != "none":
            raise SystemExit(f"kalibr.yaml: no projection written here for {dm}")
        out.append([fu * x + pu, fv * y + pv])
    return out


def main():
    d = sys.argv[1]
    with open(os.path.join(d, "points.json")) as f:
        pts = np.array(json.load(f)["points"], dtype=np.float64).reshape(-1, 1, 3)
    out = {"loaded": {}}

    fs = cv2.FileStorage(os.path.join(d, "opencv.yaml"), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise SystemExit("cv2.FileStorage could not open opencv.yaml")
    k = fs.getNode("camera_matrix").mat()
    dist = fs.getNode("distortion_coefficients").mat()
    w = int(fs.getNode("image_width").real())
    h = int(fs.getNode("image_height").real())
    fisheye_node = fs.getNode("fisheye_model")
    fisheye = int(fisheye_node.real()) if not fisheye_node.empty() else None
    fs.release()
    if k is None or dist is None:
        raise SystemExit("opencv.yaml: camera_matrix or distortion_coefficients missing")
    out["opencv"], out["opencv_behind"] = project_opencv(pts, k, dist, fisheye == 1)
    out["opencv_theta"] = opencv_theta(pts, k, dist) if fisheye == 1 else None
    out["loaded"]["opencv"] = {"K": k.tolist(), "D": dist.ravel().tolist(), "size": [w, h],
                               "fisheye_model": fisheye}

    res = camera_calibration_parsers.readCalibration(os.path.join(d, "ros.yaml"))
    if res is None:
        raise SystemExit("camera_calibration_parsers.readCalibration rejected ros.yaml")
    name, info = res
    k = np.array(info.K, dtype=np.float64).reshape(3, 3)
    dist = np.array(info.D, dtype=np.float64)
    out["ros"], _ = project_opencv(pts, k, dist, info.distortion_model == "equidistant")
    out["loaded"]["ros"] = {"name": name, "K": k.tolist(), "D": dist.tolist(),
                            "model": info.distortion_model, "size": [info.width, info.height],
                            "P": list(info.P), "R": list(info.R)}

    path = os.path.join(d, "model.cameramodel")
    out["mrcal"] = None
    if os.path.exists(path):
        m = mrcal.cameramodel(path)
        lensmodel, intrinsics = m.intrinsics()
        uv = mrcal.project(pts.reshape(-1, 3), lensmodel, intrinsics)
        out["mrcal"] = np.asarray(uv).reshape(-1, 2).tolist()
        out["loaded"]["mrcal"] = {"lensmodel": lensmodel,
                                  "intrinsics": list(map(float, intrinsics)),
                                  "size": [int(x) for x in m.imagersize()]}

    path = os.path.join(d, "kalibr.yaml")
    out["kalibr"] = None
    if os.path.exists(path):
        with open(path) as f:
            data = yaml.safe_load(f)
        kalibr_check(data)
        out["kalibr"] = kalibr_project(data["cam0"], pts)
        out["loaded"]["kalibr"] = data

    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
