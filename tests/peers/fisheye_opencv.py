#!/usr/bin/env python3
"""OpenCV's baseline on a real fisheye chessboard set (issue 32, acceptance line 2): views found by
each of OpenCV's chessboard detectors, and cv2.fisheye.calibrate (Kannala–Brandt, k1..k4) on the
corners found, with per-parameter standard deviations that OpenCV does not return.

usage: fisheye_opencv.py [--json] [--cols 8] [--rows 6] [--square 1.0] [--win 5] [--check-cond]
                         [IMAGE_OR_DIR ...]
       fisheye_opencv.py --self-check
(default: fixtures/fisheye/dtorres_fisheye_8x6/images; run from anywhere with /usr/bin/python3,
Debian's python3-opencv; the record in fixtures/fisheye/dtorres_fisheye_8x6/opencv_baseline.json is
`python3 tests/peers/fisheye_opencv.py --json > fixtures/fisheye/dtorres_fisheye_8x6/opencv_baseline.json`).

Detection, per image (grey):
- classic: findChessboardCorners(ADAPTIVE_THRESH | NORMALIZE_IMAGE), then cornerSubPix with a
  (2 win + 1)² window, 30 iterations / 0.001 px;
- sb: findChessboardCornersSB(EXHAUSTIVE | ACCURACY), as a second opinion; where both find the board,
  the RMS distance between the two corner sets (matched by nearest neighbour) is reported.

Calibration: cv2.fisheye.calibrate on the classic corners (and again on the SB corners), flags
CALIB_RECOMPUTE_EXTRINSIC | CALIB_FIX_SKEW (| CALIB_CHECK_COND with --check-cond), criteria
COUNT + EPS, 100 iterations, 1e-12. The board's points are (col·s, row·s, 0) with s = --square; the
square size only scales the translations, never the intrinsics.

Standard deviations: at OpenCV's solution, J = ∂r/∂θ of every corner's reprojection residual
(cv2.fisheye.projectPoints, central differences) over θ = (fx, fy, cx, cy, k1..k4, and every view's
rvec, tvec), poses as nuisance parameters; σ² = s²·diag((JᵀJ)⁻¹) over the intrinsics, with
s² = Σr²/(2N − P) the per-coordinate residual variance (N corners, P parameters), as cubecal's
solver and calibrateCameraExtended define it. OpenCV's own "rms" is sqrt(Σ|r|²/N) (per corner, both
coordinates together), reported as returned. "gn_step_sigma" is one further Gauss–Newton step from
OpenCV's solution, per intrinsic, in units of its σ: near 0 when OpenCV has converged, so that its
numbers are the optimum that a comparison within 3σ assumes.

--self-check: the central-difference Jacobian against the analytic one that
cv2.fisheye.projectPoints returns, on a synthetic view (exit 1 if they differ by more than 1e-6 of
its largest entry).
"""
import argparse
import glob
import json
import math
import os
import sys

import cv2
import numpy as np

cv2.setNumThreads(1)
ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
DEFAULT = os.path.join(ROOT, "fixtures", "fisheye", "dtorres_fisheye_8x6", "images")
NAMES = ["fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"]
CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
SB_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def images_of(args):
    paths = []
    for a in args or [DEFAULT]:
        if os.path.isdir(a):
            paths += sorted(p for p in glob.glob(os.path.join(a, "*"))
                            if p.lower().endswith((".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")))
        else:
            paths.append(a)
    return paths


def board(cols, rows, square):
    obj = np.zeros((cols * rows, 1, 3), np.float64)
    obj[:, 0, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square
    return obj


def detect(paths, size, win):
    views = []
    sub_criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    for path in paths:
        g = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if g is None:
            sys.exit(f"cannot read {path}")
        v = {"image": os.path.basename(path), "size": [g.shape[1], g.shape[0]]}
        ok, c = cv2.findChessboardCorners(g, size, flags=CLASSIC_FLAGS)
        v["classic"] = bool(ok)
        if ok:
            c = cv2.cornerSubPix(g, c, (win, win), (-1, -1), sub_criteria)
            v["classic_uv"] = c.reshape(-1, 2).astype(np.float64)
        ok, c = cv2.findChessboardCornersSB(g, size, flags=SB_FLAGS)
        v["sb"] = bool(ok)
        if ok:
            v["sb_uv"] = c.reshape(-1, 2).astype(np.float64)
        if v["classic"] and v["sb"]:
            a, b = v["classic_uv"], v["sb_uv"]
            d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2).min(axis=1)
            v["classic_vs_sb_rms_px"] = float(np.sqrt(np.mean(d * d)))
            v["classic_vs_sb_max_px"] = float(d.max())
        print(f"{v['image']}: classic {v['classic']}, sb {v['sb']}", file=sys.stderr)
        views.append(v)
    return views


def project(obj, rvec, tvec, k, d):
    p, _ = cv2.fisheye.projectPoints(obj, rvec.reshape(1, 1, 3), tvec.reshape(1, 1, 3), k, d)
    return p.reshape(-1, 2)


def kd(theta):
    fx, fy, cx, cy = theta[:4]
    k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return k, np.array(theta[4:8], np.float64).reshape(4, 1)


def residuals(theta, obj, uvs):
    k, d = kd(theta)
    out = []
    for i, uv in enumerate(uvs):
        pose = theta[8 + 6 * i: 14 + 6 * i]
        out.append((project(obj, pose[:3], pose[3:], k, d) - uv).ravel())
    return np.concatenate(out)


def jacobian(theta, obj, uvs):
    """Central differences; each pose column only touches its own view's rows."""
    n_views = len(uvs)
    m = 2 * obj.shape[0]
    jac = np.zeros((m * n_views, theta.size))
    steps = np.maximum(np.abs(theta), 1.0) * 1e-6
    for j in range(theta.size):
        tp, tm = theta.copy(), theta.copy()
        tp[j] += steps[j]
        tm[j] -= steps[j]
        if j < 8:
            jac[:, j] = (residuals(tp, obj, uvs) - residuals(tm, obj, uvs)) / (2 * steps[j])
        else:
            i = (j - 8) // 6
            k, d = kd(theta)
            pp, pm = tp[8 + 6 * i: 14 + 6 * i], tm[8 + 6 * i: 14 + 6 * i]
            dp = project(obj, pp[:3], pp[3:], k, d) - project(obj, pm[:3], pm[3:], k, d)
            jac[m * i: m * (i + 1), j] = dp.ravel() / (2 * steps[j])
    return jac


def theta_of_rd(rd, dist):
    """Field angle θ (rad) of a distorted normalised radius θd = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸)."""
    k1, k2, k3, k4 = dist
    t = rd
    for _ in range(50):
        t2 = t * t
        f = t * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - rd
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        t -= f / df
    return t


def calibrate(views, key, obj, image_size, check_cond):
    used = [v for v in views if v[key]]
    uvs = [v[key + "_uv"] for v in used]
    flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
    names = ["CALIB_RECOMPUTE_EXTRINSIC", "CALIB_FIX_SKEW"]
    if check_cond:
        flags |= cv2.fisheye.CALIB_CHECK_COND
        names.append("CALIB_CHECK_COND")
    objs = [obj.copy() for _ in uvs]
    imgs = [uv.reshape(-1, 1, 2).copy() for uv in uvs]
    rms, k, d, rvecs, tvecs = cv2.fisheye.calibrate(
        objs, imgs, image_size, np.zeros((3, 3)), np.zeros((4, 1)), flags=flags, criteria=CRITERIA)
    theta = np.concatenate([[k[0, 0], k[1, 1], k[0, 2], k[1, 2]], d.ravel()]
                           + [np.concatenate([np.ravel(r), np.ravel(t)]) for r, t in zip(rvecs, tvecs)])
    r = residuals(theta, obj, uvs)
    jac = jacobian(theta, obj, uvs)
    n_res, n_par = r.size, theta.size
    s2 = float(r @ r) / (n_res - n_par)
    cov = np.linalg.inv(jac.T @ jac) * s2
    sigma = np.sqrt(np.diag(cov)[:8])
    step = -np.linalg.solve(jac.T @ jac, jac.T @ r)
    per_view = np.sqrt(np.mean(r.reshape(len(uvs), -1, 2) ** 2 * 2, axis=(1, 2)))
    for v, e in zip(used, per_view):
        v[key + "_rms_px"] = float(e)
    # field angles reached by the corners used, and the image's own extremes (edge midpoints, corners)
    fx, fy, cx, cy = theta[:4]
    dist = theta[4:8]
    all_uv = np.concatenate(uvs)
    rd = np.hypot((all_uv[:, 0] - cx) / fx, (all_uv[:, 1] - cy) / fy)
    w, h = image_size
    edge = {"left": (0 - 0.5, cy), "right": (w - 0.5, cy), "top": (cx, -0.5), "bottom": (cx, h - 0.5),
            "corner_max": max(((-0.5, -0.5), (w - 0.5, -0.5), (-0.5, h - 0.5), (w - 0.5, h - 0.5)),
                              key=lambda p: math.hypot((p[0] - cx) / fx, (p[1] - cy) / fy))}
    edge_deg = {name: math.degrees(theta_of_rd(math.hypot((u - cx) / fx, (v - cy) / fy), dist))
                for name, (u, v) in edge.items()}
    return {
        "corners": key, "views": len(uvs), "points": int(sum(len(u) for u in uvs)),
        "flags": names, "criteria": {"max_count": CRITERIA[1], "eps": CRITERIA[2]},
        "rms": float(rms),
        "K": [float(x) for x in theta[:4]], "D": [float(x) for x in dist],
        "sigma": {n: float(s) for n, s in zip(NAMES, sigma)},
        "sigma_px_per_coord": math.sqrt(s2), "dof": n_res - n_par,
        "gn_step_sigma": {n: float(x / s) for n, x, s in zip(NAMES, step[:8], sigma)},
        "correlation": np.round(cov[:8, :8] / np.outer(sigma, sigma), 4).tolist(),
        "max_corner_field_angle_deg": float(math.degrees(max(theta_of_rd(x, dist) for x in rd))),
        "image_field_angle_deg": edge_deg,
    }


def self_check():
    obj = board(8, 6, 1.0)
    theta = np.array([290.0, 289.0, 400.0, 274.0, -0.03, -0.02, 0.004, 0.0004,
                      0.3, -0.2, 0.1, -3.0, -2.0, 6.0])
    uv = residuals(theta, obj, [np.zeros((obj.shape[0], 2))]).reshape(-1, 2)
    num = jacobian(theta, obj, [uv])
    k, d = kd(theta)
    _, ana = cv2.fisheye.projectPoints(obj, theta[8:11].reshape(1, 1, 3), theta[11:14].reshape(1, 1, 3), k, d)
    ana = np.asarray(ana)[:, :14]  # fx fy cx cy k1..k4 rvec tvec (then alpha, fixed here)
    err = float(np.abs(num - ana).max() / np.abs(ana).max())
    print(f"self-check: numerical vs analytic Jacobian, max relative difference {err:.2e}")
    sys.exit(0 if err < 1e-6 else 1)


def main():
    if "--self-check" in sys.argv[1:]:
        self_check()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("paths", nargs="*")
    ap.add_argument("--json", action="store_true", help="print the record as JSON on stdout")
    ap.add_argument("--cols", type=int, default=8, help="inner corners along the board's rows")
    ap.add_argument("--rows", type=int, default=6, help="inner corners along the board's columns")
    ap.add_argument("--square", type=float, default=1.0, help="square size (unit of the translations)")
    ap.add_argument("--win", type=int, default=5, help="cornerSubPix half-window, px")
    ap.add_argument("--check-cond", action="store_true", help="add CALIB_CHECK_COND")
    a = ap.parse_args()
    paths = images_of(a.paths)
    size = (a.cols, a.rows)
    views = detect(paths, size, a.win)
    sizes = {tuple(v["size"]) for v in views}
    if len(sizes) != 1:
        sys.exit(f"images of several sizes: {sorted(sizes)}")
    image_size = sizes.pop()
    obj = board(a.cols, a.rows, a.square)
    out = {
        "opencv": cv2.__version__, "numpy": np.__version__,
        "images": os.path.relpath(os.path.dirname(os.path.abspath(paths[0])), ROOT),
        "image_size": list(image_size), "inner_corners": [a.cols, a.rows], "square": a.square,
        "classic": {"flags": ["CALIB_CB_ADAPTIVE_THRESH", "CALIB_CB_NORMALIZE_IMAGE"],
                    "corner_subpix": {"win": [a.win, a.win], "max_iter": 30, "eps": 0.001}},
        "sb": {"flags": ["CALIB_CB_EXHAUSTIVE", "CALIB_CB_ACCURACY"]},
        "found": {"images": len(views), "classic": sum(v["classic"] for v in views),
                  "sb": sum(v["sb"] for v in views),
                  "either": sum(v["classic"] or v["sb"] for v in views)},
    }
    out["calibration"] = calibrate(views, "classic", obj, image_size, a.check_cond)
    if out["found"]["sb"] >= 3:
        out["calibration_sb"] = calibrate(views, "sb", obj, image_size, a.check_cond)
    out["views"] = [{k: v[k] for k in v if not k.endswith("_uv") and k != "size"} for v in views]
    if a.json:
        json.dump(out, sys.stdout, indent=1)
        print()
        return
    f = out["found"]
    print(f"OpenCV {out['opencv']}, {f['images']} images {image_size[0]}×{image_size[1]}, board "
          f"{a.cols}×{a.rows} inner corners: classic found {f['classic']}, SB found {f['sb']}")
    for key in ("calibration", "calibration_sb"):
        c = out.get(key)
        if not c:
            continue
        print(f"\n{key} on {c['corners']} corners ({c['views']} views, {c['points']} points): "
              f"rms {c['rms']:.4f} px (OpenCV's), σ per coordinate {c['sigma_px_per_coord']:.4f} px")
        for n, x in zip(NAMES, c["K"] + c["D"]):
            print(f"  {n:3s} {x:14.6f} ± {c['sigma'][n]:.6f}   (GN step {c['gn_step_sigma'][n]:+.3f} σ)")
        print(f"  corners reach {c['max_corner_field_angle_deg']:.1f}° off axis; image edges: "
              + ", ".join(f"{k} {v:.1f}°" for k, v in c["image_field_angle_deg"].items()))


if __name__ == "__main__":
    main()
