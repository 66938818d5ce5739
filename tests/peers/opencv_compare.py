#!/usr/bin/env python3
"""Compare OpenCV's chessboard detectors (and optionally cubecal's) with the exact ground truth of
frames rendered by `cubecal render`.

Everything about the scene comes from the ground-truth JSON next to each frame (`frame_NNN.json`):
a face's grid size is max(row, col) + 1 over its corners, its plane is fitted to its corners' `xyz`,
the camera centre in rig coordinates is -R^T t from `cam_from_rig` (X_cam = R X_rig + t).

Per frame, every face whose corners are ALL visible in the ground truth ("fully visible face") is
evaluated:

* its angle from frontal: the angle between the face's normal line and the ray from the camera
  centre to the face centre (0 = seen head-on, 90 = edge-on);
* OpenCV on a masked copy of the frame in which everything outside that face's board region is a
  uniform grey at the region's mean level. The region is the face's corner grid grown by
  MASK_GROWTH_SQUARES squares on every side (the outer squares end one square out, the white margin
  continues), projected exactly with the ground-truth camera. OpenCV's detectors find one board of a
  known size per call and cannot tell the faces apart, so masking is a help cubecal does not get.
  (a) findChessboardCorners(ADAPTIVE_THRESH | NORMALIZE_IMAGE) + cornerSubPix, with two windows;
  (b) findChessboardCornersSB(EXHAUSTIVE | ACCURACY).
  A face counts as detected when the call succeeds and every returned corner lies within TOL_PX of
  a distinct ground-truth corner of that face. OpenCV's corner order is ambiguous (a board may be
  reported rotated or mirrored), so corners are matched by position, not by index: generous to
  OpenCV, as an ordering error is never counted against it.
* cubecal from the output of `cubecal detect --json` (optional): a face counts as detected when
  cubecal reports it; every reported corner is looked up by (face, row, col) in the ground truth,
  and one that is more than TOL_PX away or not visible there is MISLABELLED.

Times are taken around the detector call alone (plus cornerSubPix for (a)): wall time with
time.perf_counter, and the calling thread's CPU time (OpenCV runs single-threaded here, --threads 1),
which a busy shared machine disturbs less.
OpenCV's per-frame time is the sum over the fully visible faces of the frame (the masks come from
the ground truth, which a real user would not have); cubecal's is its own `time_ms` per image.

Run `--self-check` to test the metric code against the ground truth itself.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

try:
    import cv2
except ImportError:  # --self-check and --help work without OpenCV
    cv2 = None

TOL_PX = 1.0
MASK_GROWTH_SQUARES = 1.5
BUCKETS = [(0.0, 45.0, "< 45°"), (45.0, 60.0, "45–60°"), (60.0, 75.0, "60–75°"), (75.0, 90.01, "≥ 75°")]
SUBPIX_WINDOWS = [(5, 5), (11, 11)]
SUBPIX_CRITERIA = (3, 30, 0.001)  # cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 30 its, 0.001 px


# ----------------------------------------------------------------------------------------------
# Ground truth


@dataclass
class Camera:
    k: np.ndarray  # 3x3
    dist: np.ndarray  # OpenCV order k1 k2 p1 p2 k3 [k4 k5 k6], padded to 8
    size: tuple[int, int]  # (width, height)

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """OpenCV's Brown–Conrady (rational) distortion of normalised coordinates."""
        k1, k2, p1, p2, k3, k4, k5, k6 = self.dist
        r2 = x * x + y * y
        radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def to_pixel(self, xd: np.ndarray, yd: np.ndarray) -> np.ndarray:
        k = self.k
        return np.stack([k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]], axis=-1)

    def locally_invertible(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Whether the distortion's Jacobian determinant is positive at (x, y): false beyond the fold
        of a strong barrel distortion, where projecting a point gives a pixel on the wrong side."""
        h = 1e-6
        xa, ya = self.distort(x + h, y)
        xb, yb = self.distort(x - h, y)
        xc, yc = self.distort(x, y + h)
        xe, ye = self.distort(x, y - h)
        det = (xa - xb) * (yc - ye) - (xc - xe) * (ya - yb)
        return det > 0


@dataclass
class Face:
    name: str
    index: int
    rows: int
    cols: int
    xyz: np.ndarray  # rows x cols x 3
    uv: np.ndarray  # rows x cols x 2 (nan where behind the camera)
    visible: np.ndarray  # rows x cols bool

    @property
    def fully_visible(self) -> bool:
        return bool(self.visible.all())


@dataclass
class Frame:
    name: str  # frame_NNN
    png: Path
    camera: Camera
    rot: np.ndarray  # cam_from_rig
    t: np.ndarray
    faces: list[Face]

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in rig coordinates."""
        return -self.rot.T @ self.t

    def angle_deg(self, face: Face) -> float:
        pts = face.xyz.reshape(-1, 3)
        c = pts.mean(axis=0)
        normal = np.linalg.svd(pts - c)[2][2]
        ray = c - self.centre
        cos = abs(float(normal @ ray)) / float(np.linalg.norm(ray))
        return math.degrees(math.acos(min(1.0, cos)))

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels of rig points (..., 3), and whether each projection is trustworthy (in front of the
        camera and on the invertible side of the distortion)."""
        pc = xyz @ self.rot.T + self.t
        z = pc[..., 2]
        ok = z > 1e-9
        zs = np.where(ok, z, 1.0)
        x, y = pc[..., 0] / zs, pc[..., 1] / zs
        ok &= self.camera.locally_invertible(x, y)
        return self.camera.to_pixel(*self.camera.distort(x, y)), ok


def load_frame(json_path: Path) -> Frame:
    gt = json.loads(json_path.read_text())
    cam = gt["camera"]
    dist = np.zeros(8)
    coeffs = cam["distortion_coefficients"]
    dist[: len(coeffs)] = coeffs
    camera = Camera(np.array(cam["camera_matrix"], float), dist, tuple(cam["image_size"]))
    by_face: dict[int, list[dict]] = {}
    for c in gt["corners"]:
        by_face.setdefault(c["face_index"], []).append(c)
    faces = []
    for index in sorted(by_face):
        cs = by_face[index]
        rows = max(c["row"] for c in cs) + 1
        cols = max(c["col"] for c in cs) + 1
        xyz = np.full((rows, cols, 3), np.nan)
        uv = np.full((rows, cols, 2), np.nan)
        vis = np.zeros((rows, cols), bool)
        for c in cs:
            xyz[c["row"], c["col"]] = c["xyz"]
            if c["uv"] is not None:
                uv[c["row"], c["col"]] = c["uv"]
            vis[c["row"], c["col"]] = c["visible"]
        if np.isnan(xyz).any():
            raise ValueError(f"{json_path}: face {cs[0]['face']} does not list every corner of its grid")
        faces.append(Face(cs[0]["face"], index, rows, cols, xyz, uv, vis))
    pose = gt["cam_from_rig"]
    return Frame(
        json_path.stem,
        json_path.with_suffix(".png"),
        camera,
        np.array(pose["rotation"], float),
        np.array(pose["translation"], float),
        faces,
    )


def load_frames(frames_dir: Path) -> list[Frame]:
    paths = sorted(frames_dir.glob("frame_*.json"))
    if not paths:
        raise SystemExit(f"error: no frame_*.json in {frames_dir}: render frames with `cubecal render` first")
    return [load_frame(p) for p in paths]


# ----------------------------------------------------------------------------------------------
# Masking


def board_polygon(frame: Frame, face: Face, growth: float = MASK_GROWTH_SQUARES) -> np.ndarray:
    """The face's corner grid grown by `growth` squares on every side, projected: boundary points
    (N x 2). A boundary point whose projection is not trustworthy (behind the camera or beyond the
    distortion's fold) is pulled in toward the grid until it is; the grid itself always is."""
    o = face.xyz[0, 0]
    a = (face.xyz[0, -1] - o) / (face.cols - 1)  # one square along a row (col direction)
    b = (face.xyz[-1, 0] - o) / (face.rows - 1)  # one square along a column (row direction)
    n = 24
    cs = np.linspace(-growth, face.cols - 1 + growth, n)
    rs = np.linspace(-growth, face.rows - 1 + growth, n)
    lo_c, hi_c, lo_r, hi_r = -growth, face.cols - 1 + growth, -growth, face.rows - 1 + growth
    border = (
        [(lo_r, c) for c in cs]
        + [(r, hi_c) for r in rs]
        + [(hi_r, c) for c in cs[::-1]]
        + [(r, lo_c) for r in rs[::-1]]
    )
    rc_centre = np.array([(face.rows - 1) / 2, (face.cols - 1) / 2])
    points = []
    for rc in np.array(border):
        for s in np.linspace(1.0, 0.0, 41):
            r, c = rc_centre + s * (rc - rc_centre)
            uv, ok = frame.project(o + c * a + r * b)
            inside_grid = 0 <= r <= face.rows - 1 and 0 <= c <= face.cols - 1
            if ok or inside_grid:
                points.append(uv)
                break
    return np.array(points)


def masked_image(img: np.ndarray, frame: Frame, face: Face) -> tuple[np.ndarray, np.ndarray]:
    """The frame with everything outside the face's board region set to the region's mean level;
    also returns the region mask."""
    h, w = img.shape
    # Far-off points (near the camera plane) only need to stay far off; keep them in int32 range.
    poly = np.clip(board_polygon(frame, face), [-2 * w, -2 * h], [3 * w, 3 * h])
    hull = cv2.convexHull(np.round(poly * 16).astype(np.int32))
    mask = np.zeros(img.shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 255, lineType=cv2.LINE_8, shift=4)
    inside = mask > 0
    level = round(float(img[inside].mean())) if inside.any() else 128
    out = np.full_like(img, level)
    out[inside] = img[inside]
    return out, mask


# ----------------------------------------------------------------------------------------------
# Metrics


def min_cost_assignment(cost: np.ndarray) -> np.ndarray:
    """Rows-to-columns assignment of least total cost (Hungarian method with potentials,
    O(n² m)), for an n × m cost matrix with n ≤ m. Returns the column of each row."""
    n, m = cost.shape
    inf = float("inf")
    u, v = [0.0] * (n + 1), [0.0] * (m + 1)
    p, way = [0] * (m + 1), [0] * (m + 1)  # p[j]: row (1-based) assigned to column j
    for i in range(1, n + 1):
        p[0], j0 = i, 0
        minv, used = [inf] * (m + 1), [False] * (m + 1)
        while True:
            used[j0] = True
            i0, delta, j1 = p[j0], inf, 0
            for j in range(1, m + 1):
                if not used[j]:
                    cur = cost[i0 - 1, j - 1] - u[i0] - v[j]
                    if cur < minv[j]:
                        minv[j], way[j] = cur, j0
                    if minv[j] < delta:
                        delta, j1 = minv[j], j
            for j in range(m + 1):
                if used[j]:
                    u[p[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if p[j0] == 0:
                break
        while j0:
            j1 = way[j0]
            p[j0] = p[j1]
            j0 = j1
    col = np.zeros(n, int)
    for j in range(1, m + 1):
        if p[j]:
            col[p[j] - 1] = j - 1
    return col


def match_to_truth(found: np.ndarray, truth: np.ndarray, tol: float = TOL_PX) -> np.ndarray | None:
    """Match every found corner (N x 2) to a distinct truth corner (M x 2) within `tol` px.
    Returns the matched distances, or None when no such matching exists. The matching is the one of
    least total squared distance among those with the most pairs within `tol` (a pair beyond `tol`
    costs more than any set of pairs within it), so it is optimal, not greedy."""
    found = np.asarray(found, float).reshape(-1, 2)
    truth = np.asarray(truth, float).reshape(-1, 2)
    if len(found) == 0 or len(found) > len(truth) or not np.isfinite(found).all():
        return None
    d = np.linalg.norm(found[:, None, :] - truth[None, :, :], axis=2)
    feasible = d <= tol
    if not feasible.any(axis=1).all():
        return None  # the common case of a bad detection: decided without the assignment
    penalty = 1.0 + len(found) * tol * tol
    cost = np.where(feasible, d * d, penalty)
    col = min_cost_assignment(cost)
    e = d[np.arange(len(found)), col]
    return e if (e <= tol).all() else None


@dataclass
class Tally:
    """What one detector did over one image set."""

    label: str
    faces: list[dict] = field(default_factory=list)  # one per fully visible face evaluated
    errors: list[float] = field(default_factory=list)  # matched/correct corners of detected faces
    frame_ms: dict[str, float] = field(default_factory=dict)
    mislabelled: int | None = None  # cubecal only
    extra: dict = field(default_factory=dict)

    frame_cpu_ms: dict[str, float] = field(default_factory=dict)

    def add_face(self, record: dict, errors: np.ndarray | None, frame: str) -> None:
        self.faces.append(record)
        if errors is not None:
            self.errors.extend(float(e) for e in errors)
        self.frame_ms[frame] = self.frame_ms.get(frame, 0.0) + record["ms"]
        self.frame_cpu_ms[frame] = self.frame_cpu_ms.get(frame, 0.0) + record["cpu_ms"]

    def rate(self, pred) -> tuple[int, int]:
        sel = [f for f in self.faces if pred(f)]
        return sum(f["detected"] for f in sel), len(sel)

    def summary(self, max_angle: float) -> dict:
        s = {"label": self.label}
        s["detected"], s["faces"] = self.rate(lambda f: True)
        s["detected_below_max_angle"], s["faces_below_max_angle"] = self.rate(lambda f: f["angle_deg"] < max_angle)
        s["buckets"] = []
        for lo, hi, name in BUCKETS:
            d, n = self.rate(lambda f, lo=lo, hi=hi: lo <= f["angle_deg"] < hi)
            s["buckets"].append({"bucket": name, "detected": d, "faces": n})
        names = sorted({f["face"] for f in self.faces})
        s["per_face"] = {}
        for name in names:
            d, n = self.rate(lambda f, name=name: f["face"] == name)
            s["per_face"][name] = {"detected": d, "faces": n}
        errs = np.array(self.errors)
        s["corners"] = len(errs)
        s["rms_px"] = float(np.sqrt(np.mean(errs**2))) if len(errs) else None
        s["max_px"] = float(errs.max()) if len(errs) else None
        s["found_but_off"] = sum(1 for f in self.faces if f.get("found") and not f["detected"])
        s["mislabelled"] = self.mislabelled
        face_ms = [f["ms"] for f in self.faces if f.get("ms") is not None]
        frame_ms = list(self.frame_ms.values())
        s["median_ms_per_frame"] = statistics.median(frame_ms) if frame_ms else None
        s["mean_ms_per_frame"] = statistics.fmean(frame_ms) if frame_ms else None
        s["median_ms_per_face"] = statistics.median(face_ms) if face_ms else None
        s["mean_ms_per_face"] = statistics.fmean(face_ms) if face_ms else None
        face_cpu = [f["cpu_ms"] for f in self.faces if f.get("cpu_ms") is not None]
        frame_cpu = list(self.frame_cpu_ms.values())
        s["median_cpu_ms_per_frame"] = statistics.median(frame_cpu) if frame_cpu else None
        s["median_cpu_ms_per_face"] = statistics.median(face_cpu) if face_cpu else None
        s.update(self.extra)
        return s


# ----------------------------------------------------------------------------------------------
# Detectors


class Clock:
    """Wall time (time.perf_counter) and this thread's CPU time (time.thread_time) of a block, in ms.
    The CPU time is the steadier figure on a shared machine; with cv2.setNumThreads(1) OpenCV does
    all its work on the calling thread, so it is the whole cost."""

    def __enter__(self):
        self.wall0, self.cpu0 = time.perf_counter(), time.thread_time()
        return self

    def __exit__(self, *exc):
        self.wall = (time.perf_counter() - self.wall0) * 1e3
        self.cpu = (time.thread_time() - self.cpu0) * 1e3
        return False


def run_opencv(frames: list[Frame], save_masked: Path | None, save_count: int) -> list[Tally]:
    classic = {w: Tally(f"OpenCV findChessboardCorners + cornerSubPix {w[0]}×{w[1]}") for w in SUBPIX_WINDOWS}
    sb = Tally("OpenCV findChessboardCornersSB")
    flags_classic = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    flags_sb = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, SUBPIX_CRITERIA[1], SUBPIX_CRITERIA[2])
    # Warm-up, so that one-time initialisation is not timed.
    warm = np.full((64, 64), 128, np.uint8)
    cv2.findChessboardCorners(warm, (3, 3), flags=flags_classic)
    cv2.findChessboardCornersSB(warm, (3, 3), flags=flags_sb)
    saved = 0
    for k, frame in enumerate(frames):
        img = cv2.imread(str(frame.png), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SystemExit(f"error: cannot read {frame.png}")
        for face in frame.faces:
            if not face.fully_visible:
                continue
            angle = frame.angle_deg(face)
            truth = face.uv.reshape(-1, 2)
            masked, _ = masked_image(img, frame, face)
            if save_masked is not None and saved < save_count:
                save_masked.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(save_masked / f"{frame.name}_{face.name}.png"), masked)
                saved += 1
            size = (face.cols, face.rows)
            base = {"frame": frame.name, "face": face.name, "angle_deg": angle}

            with Clock() as find:
                ok, corners = cv2.findChessboardCorners(masked, size, flags=flags_classic)
            for w, tally in classic.items():
                ms, cpu_ms, errs = find.wall, find.cpu, None
                if ok:
                    with Clock() as sub:
                        c = cv2.cornerSubPix(masked, corners.copy(), w, (-1, -1), criteria)
                    ms, cpu_ms = ms + sub.wall, cpu_ms + sub.cpu
                    errs = match_to_truth(c.reshape(-1, 2), truth)
                rec = dict(base, found=bool(ok), detected=errs is not None, ms=ms, cpu_ms=cpu_ms)
                tally.add_face(rec, errs, frame.name)

            with Clock() as clock:
                ok, corners = cv2.findChessboardCornersSB(masked, size, flags=flags_sb)
            errs = match_to_truth(corners.reshape(-1, 2), truth) if ok else None
            rec = dict(base, found=bool(ok), detected=errs is not None, ms=clock.wall, cpu_ms=clock.cpu)
            sb.add_face(rec, errs, frame.name)
        print(f"  {frame.name}: done ({k + 1}/{len(frames)})", file=sys.stderr, flush=True)
    return [classic[w] for w in SUBPIX_WINDOWS] + [sb]


def load_cubecal(path: Path) -> dict[str, dict]:
    """`cubecal detect --json` output, keyed by image file stem (frame_NNN)."""
    data = json.loads(path.read_text())
    if not isinstance(data, list):
        raise SystemExit(f"error: {path}: expected a JSON array of per-image results")
    out = {}
    for rec in data:
        stem = Path(rec["image"]).stem
        faces = {}
        for f in rec.get("faces", []):
            faces[f["face"]] = [
                (int(c["row"]), int(c["col"]), np.array(c["uv"], float), c.get("xyz")) for c in f["corners"]
            ]
        out[stem] = {
            "faces": faces,
            "rejected": [r.get("reason", "") for r in rec.get("rejected", [])],
            "time_ms": rec.get("time_ms"),
        }
    return out


def run_cubecal(frames: list[Frame], results: dict[str, dict]) -> Tally:
    tally = Tally("cubecal detect")
    mislabelled = 0
    xyz_mismatch = 0
    partial_reported = 0
    missing_images = 0
    rejected = 0
    unknown_faces = 0
    partial_correct = 0
    for frame in frames:
        res = results.get(frame.name)
        if res is None:
            missing_images += 1
            res = {"faces": {}, "rejected": [], "time_ms": None}
        rejected += len(res["rejected"])
        if res["time_ms"] is not None:
            tally.frame_ms[frame.name] = float(res["time_ms"])
        by_name = {f.name: f for f in frame.faces}
        for name in res["faces"]:
            if name not in by_name:
                unknown_faces += 1
        for face in frame.faces:
            reported = res["faces"].get(face.name)
            good = []
            if reported is not None:
                for row, col, uv, xyz in reported:
                    inside = 0 <= row < face.rows and 0 <= col < face.cols
                    if not inside or not face.visible[row, col]:
                        mislabelled += 1
                        continue
                    e = float(np.linalg.norm(uv - face.uv[row, col]))
                    if e > TOL_PX:
                        mislabelled += 1
                        continue
                    if xyz is not None and np.linalg.norm(np.array(xyz, float) - face.xyz[row, col]) > 1e-6:
                        xyz_mismatch += 1
                    good.append(e)
            if not face.fully_visible:
                # Errors are summarised over fully visible faces only, the faces OpenCV is run on.
                partial_reported += reported is not None
                partial_correct += len(good)
                continue
            rec = {
                "frame": frame.name,
                "face": face.name,
                "angle_deg": frame.angle_deg(face),
                "detected": reported is not None,
                "corners_reported": 0 if reported is None else len(reported),
                "corners_visible": int(face.visible.sum()),
            }
            tally.faces.append(rec)
            tally.errors.extend(good)
    tally.mislabelled = mislabelled
    tally.extra = {
        "xyz_disagrees_with_truth": xyz_mismatch,
        "partially_visible_faces_reported": partial_reported,
        "correct_corners_on_partially_visible_faces": partial_correct,
        "images_missing_from_cubecal_output": missing_images,
        "rejected_grids": rejected,
        "unknown_face_names": unknown_faces,
    }
    return tally


# ----------------------------------------------------------------------------------------------
# Report


def fmt_rate(d: int, n: int) -> str:
    return f"{d}/{n} ({100.0 * d / n:.0f} %)" if n else "–"


def fmt_num(x, digits: int) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def table(summaries: list[dict], max_angle: float) -> str:
    rows: list[tuple[str, list[str]]] = []
    rows.append(("faces detected / fully visible", [fmt_rate(s["detected"], s["faces"]) for s in summaries]))
    rows.append(
        (
            f"… seen at < {max_angle:g}°",
            [fmt_rate(s["detected_below_max_angle"], s["faces_below_max_angle"]) for s in summaries],
        )
    )
    for k, (_, _, name) in enumerate(BUCKETS):
        rows.append((f"… {name}", [fmt_rate(s["buckets"][k]["detected"], s["buckets"][k]["faces"]) for s in summaries]))
    names = sorted({n for s in summaries for n in s["per_face"]})
    for name in names:
        rows.append(
            (
                f"… face {name}",
                [
                    fmt_rate(
                        s["per_face"].get(name, {}).get("detected", 0), s["per_face"].get(name, {}).get("faces", 0)
                    )
                    for s in summaries
                ],
            )
        )
    rows.append(
        (
            "found but > 1 px off (not counted)",
            [str(s["found_but_off"]) if "found_but_off" in s and s["mislabelled"] is None else "–" for s in summaries],
        )
    )
    rows.append(("corners (matched / correct)", [str(s["corners"]) for s in summaries]))
    rows.append(("RMS error, px", [fmt_num(s["rms_px"], 3) for s in summaries]))
    rows.append(("max error, px", [fmt_num(s["max_px"], 3) for s in summaries]))
    rows.append(
        ("mislabelled corners", ["–" if s["mislabelled"] is None else str(s["mislabelled"]) for s in summaries])
    )
    rows.append(("median wall time / frame, ms", [fmt_num(s["median_ms_per_frame"], 1) for s in summaries]))
    rows.append(("median wall time / face, ms", [fmt_num(s["median_ms_per_face"], 1) for s in summaries]))
    rows.append(("median CPU time / frame, ms", [fmt_num(s["median_cpu_ms_per_frame"], 1) for s in summaries]))
    rows.append(("median CPU time / face, ms", [fmt_num(s["median_cpu_ms_per_face"], 1) for s in summaries]))
    header = ["metric"] + [s["label"] for s in summaries]
    widths = [
        max(len(header[i]), *(len(r[0]) if i == 0 else len(r[1][i - 1]) for r in rows)) for i in range(len(header))
    ]

    def line(cells):
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"

    out = [line(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    out += [line([r[0]] + r[1]) for r in rows]
    return "\n".join(out)


def better_window(summaries: list[dict], max_angle: float) -> str:
    """The better cornerSubPix window: more faces detected below max_angle, then lower RMS."""
    classic = summaries[: len(SUBPIX_WINDOWS)]

    def key(s: dict) -> tuple:
        return (s["detected_below_max_angle"], s["detected"], -(s["rms_px"] or 1e9))

    best = max(classic, key=key)
    if all(key(s) == key(best) for s in classic):
        return "neither (a tie)"
    return best["label"]


# ----------------------------------------------------------------------------------------------
# Self-check of the metric code


def self_check(frames: list[Frame]) -> int:
    failures: list[str] = []
    checks = 0

    def check(cond: bool, what: str) -> None:
        nonlocal checks
        checks += 1
        if not cond:
            failures.append(what)

    rng = np.random.default_rng(0)
    # The assignment is optimal: against brute force on small random problems.

    for _ in range(200):
        n = int(rng.integers(1, 5))
        m = int(rng.integers(n, 6))
        cost = rng.random((n, m))
        col = min_cost_assignment(cost)
        best = min(sum(cost[i, c[i]] for i in range(n)) for c in itertools.permutations(range(m), n))
        check(
            len(set(col)) == n and abs(sum(cost[i, col[i]] for i in range(n)) - best) < 1e-12,
            f"assignment not optimal for {cost}",
        )
    # The fold of a barrel distortion k1 = -0.3 is at r = 1/sqrt(0.9) = 1.054 (d(r(1 + k1 r²))/dr = 0).
    fold = Camera(np.eye(3), np.array([-0.3, 0, 0, 0, 0, 0, 0, 0.0]), (100, 100))
    got = fold.locally_invertible(np.array([0.5, 1.04, 1.07, 0.0]), np.array([0.0, 0.0, 0.0, 1.2]))
    check(got.tolist() == [True, True, False, False], f"fold test gave {got}")
    # Two found corners both nearest to truth 0: the optimal matching pairs them with 0 and 1.
    e = match_to_truth(np.array([[0.4, 0.0], [0.1, 0.0]]), np.array([[0.0, 0.0], [0.9, 0.0]]))
    check(e is not None and np.allclose(sorted(e), [0.1, 0.5]), f"crowded matching gave {e}")
    evaluated = 0
    for frame in frames:
        for face in frame.faces:
            vis = face.visible
            if vis.any():
                uv, ok = frame.project(face.xyz[vis])
                check(bool(ok.all()), f"{frame.name} {face.name}: a visible corner projects as untrustworthy")
                err = float(np.abs(uv - face.uv[vis]).max())
                check(err < 1e-6, f"{frame.name} {face.name}: own projection differs from GT uv by {err:.2e} px")
            if not face.fully_visible:
                continue
            evaluated += 1
            truth = face.uv.reshape(-1, 2)
            perm = rng.permutation(len(truth))
            e = match_to_truth(truth[perm], truth)
            check(
                e is not None and float(np.max(e)) == 0.0, f"{frame.name} {face.name}: GT vs GT is not an exact match"
            )
            e = match_to_truth(truth[perm] + [0.6, 0.0], truth)
            check(
                e is not None and np.allclose(e, 0.6),
                f"{frame.name} {face.name}: a 0.6 px shift is not measured as 0.6 px",
            )
            bad = truth.copy()
            bad[3] += [1.5, 0.0]
            check(match_to_truth(bad, truth) is None, f"{frame.name} {face.name}: a corner 1.5 px off is accepted")
            dup = truth.copy()
            dup[1] = dup[0] + [0.1, 0.0]
            check(match_to_truth(dup, truth) is None, f"{frame.name} {face.name}: two corners matched to one GT corner")
            flipped = truth.reshape(face.rows, face.cols, 2)[::-1, ::-1].reshape(-1, 2)
            e = match_to_truth(flipped, truth)
            check(
                e is not None and float(np.max(e)) == 0.0, f"{frame.name} {face.name}: a reversed order is not matched"
            )
            a = frame.angle_deg(face)
            check(0.0 <= a <= 90.0, f"{frame.name} {face.name}: angle {a} outside 0..90")
            poly = board_polygon(frame, face)
            # Every GT corner lies inside the mask polygon.
            if cv2 is not None:
                hull = cv2.convexHull(poly.astype(np.float32))
                inside = [cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0 for u, v in truth]
                check(all(inside), f"{frame.name} {face.name}: a GT corner lies outside the mask")
    check(evaluated > 0, "no fully visible face to check")

    # Angle: a camera on a face's normal through its centre sees it at 0°, one in its plane at 90°.
    f0 = next(f for fr in frames for f in fr.faces)
    fr0 = frames[0]
    pts = f0.xyz.reshape(-1, 3)
    c = pts.mean(axis=0)
    n = np.linalg.svd(pts - c)[2][2]
    for dist_dir, want in [(n, 0.0), (-n, 0.0), (f0.xyz[0, -1] - f0.xyz[0, 0], 90.0)]:
        eye = c + 500.0 * dist_dir / np.linalg.norm(dist_dir)
        probe = Frame(fr0.name, fr0.png, fr0.camera, np.eye(3), -eye, fr0.faces)
        got = probe.angle_deg(f0)
        check(abs(got - want) < 1e-6, f"angle with the camera at {want}° measured as {got}°")

    # cubecal's JSON format, on a hand-made sample derived from the first frame's ground truth:
    # the first fully visible face reported correctly, one corner of it with a wrong (row, col).
    frame = next(fr for fr in frames if any(f.fully_visible for f in fr.faces))
    face = next(f for f in frame.faces if f.fully_visible)
    corners = [
        {"row": r, "col": c, "xyz": face.xyz[r, c].tolist(), "uv": face.uv[r, c].tolist()}
        for r in range(face.rows)
        for c in range(face.cols)
    ]
    corners[0]["row"], corners[0]["col"] = 1, 1  # a duplicate label at the wrong place
    corners[2]["xyz"][0] += 1.0  # right place and label, but cubecal's xyz disagrees
    sample = [
        {
            "image": str(frame.png),
            "width": frame.camera.size[0],
            "height": frame.camera.size[1],
            "faces": [{"face": face.name, "corners": corners}],
            "rejected": [{"reason": "grid size matches no face"}],
            "time_ms": 12.5,
        }
    ]
    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "detect.json"
        p.write_text(json.dumps(sample, indent=1))
        tally = run_cubecal([frame], load_cubecal(p))
    s = tally.summary(75.0)
    check(s["detected"] == 1, f"cubecal sample: {s['detected']} faces detected, expected 1")
    check(tally.mislabelled == 1, f"cubecal sample: {tally.mislabelled} mislabelled, expected 1")
    check(s["corners"] == face.rows * face.cols - 1, f"cubecal sample: {s['corners']} correct corners")
    check(s["rms_px"] == 0.0, f"cubecal sample: RMS {s['rms_px']}, expected 0")
    check(s["rejected_grids"] == 1 and s["median_ms_per_frame"] == 12.5, "cubecal sample: rejected/time not read")
    check(s["xyz_disagrees_with_truth"] == 1, "cubecal sample: the relabelled corner's xyz should disagree")

    for f in failures:
        print(f"self-check FAILED: {f}", file=sys.stderr)
    print(f"self-check: {checks - len(failures)} passed, {len(failures)} failed ({evaluated} fully visible faces)")
    return 1 if failures else 0


# ----------------------------------------------------------------------------------------------


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=Path, required=True, help="directory of frame_NNN.png + frame_NNN.json")
    ap.add_argument("--rig", type=Path, help="rig TOML (not needed: everything comes from the ground truth)")
    ap.add_argument("--cubecal-json", type=Path, help="output of `cubecal detect --json` over the same frames")
    ap.add_argument("--max-angle", type=float, default=75.0, help="headline rate over faces seen below this angle (°)")
    ap.add_argument("--json", type=Path, help="write a machine-readable summary here")
    ap.add_argument("--title", default=None, help="title of the printed tables")
    ap.add_argument("--threads", type=int, default=1, help="cv2.setNumThreads (default 1: per-core times)")
    ap.add_argument("--save-masked", type=Path, help="save the first masked images here (PNG)")
    ap.add_argument("--save-masked-count", type=int, default=3)
    ap.add_argument("--no-opencv", action="store_true", help="evaluate cubecal only")
    ap.add_argument("--self-check", action="store_true", help="test the metric code on the ground truth and exit")
    args = ap.parse_args()

    frames = load_frames(args.frames)
    if args.self_check:
        return self_check(frames)

    tallies: list[Tally] = []
    info = {"frames_dir": str(args.frames), "n_frames": len(frames), "max_angle_deg": args.max_angle, "tol_px": TOL_PX}
    info["image_size"] = list(frames[0].camera.size)
    if not args.no_opencv:
        if cv2 is None:
            raise SystemExit("error: OpenCV (cv2) is not installed: pip install opencv-python-headless")
        cv2.setNumThreads(args.threads)
        info.update(opencv_version=cv2.__version__, opencv_threads=cv2.getNumThreads())
        info["mask_growth_squares"] = MASK_GROWTH_SQUARES
        print(
            f"OpenCV {cv2.__version__} ({cv2.getNumThreads()} thread(s)) on {len(frames)} frames in {args.frames}",
            file=sys.stderr,
        )
        tallies += run_opencv(frames, args.save_masked, args.save_masked_count)
    if args.cubecal_json is not None:
        tallies.append(run_cubecal(frames, load_cubecal(args.cubecal_json)))
    summaries = [t.summary(args.max_angle) for t in tallies]

    n_faces = sum(f.fully_visible for fr in frames for f in fr.faces)
    title = args.title or str(args.frames)
    print(f"\n## {title}\n")
    print(
        f"{len(frames)} frames {info['image_size'][0]}×{info['image_size'][1]}, {n_faces} fully visible faces; "
        f"detected = every corner within {TOL_PX:g} px of a distinct ground-truth corner (OpenCV, matched by position) "
        f"or reported at all (cubecal)."
    )
    if "opencv_version" in info:
        print(f"OpenCV {info['opencv_version']}, {info['opencv_threads']} thread(s).")
    print()
    print(table(summaries, args.max_angle))
    if not args.no_opencv:
        print(f"\nBetter cornerSubPix window on this set: {better_window(summaries, args.max_angle)}")
    for s in summaries:
        if s["mislabelled"] is not None:
            extra = ", ".join(
                f"{k.replace('_', ' ')} {s[k]}"
                for k in (
                    "partially_visible_faces_reported",
                    "correct_corners_on_partially_visible_faces",
                    "rejected_grids",
                    "xyz_disagrees_with_truth",
                    "images_missing_from_cubecal_output",
                    "unknown_face_names",
                )
            )
            print(f"cubecal: {extra}")
    if args.json is not None:
        per_face = {t.label: t.faces for t in tallies}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.json.with_suffix(".tmp")
        tmp.write_text(json.dumps({"info": info, "summaries": summaries, "faces": per_face}, indent=1))
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
