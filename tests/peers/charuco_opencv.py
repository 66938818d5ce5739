#!/usr/bin/env python3
"""OpenCV's ChArUco detector on images, for cubecal's tests (tests/detect_charuco.rs).

Usage: charuco_opencv.py BOARDS.json IMAGE...
       charuco_opencv.py --calibrate VIEWS.json
       charuco_opencv.py --rasterise FACE.svg OUT.png PX_PER_MM
       charuco_opencv.py --generate BOARDS.json NAME OUT.png PX_PER_SQUARE MARGIN_PX


BOARDS.json: {"boards": [{"name": ..., "dictionary": "DICT_5X5_250", "squares": [SX, SY],
"square": S, "marker": M, "ids": [...]}, ...]} (one per ChArUco face, OpenCV's layout).
Prints one JSON object: {"cv2": version, "images": [{"path": ..., "markers": [[id, [[x, y] x4]], ...],
"boards": {name: [[corner_id, x, y], ...]}}]}. Each board is interpolated from the markers with its
own ids (OpenCV's default: two markers per corner), corners refined by cornerSubPix as
CharucoDetector does. Works with OpenCV 4.6 (Debian bookworm: detectMarkers +
interpolateCornersCharuco) and >= 4.7 (CharucoDetector).

--calibrate: VIEWS.json {"image_size": [w, h], "rational": bool, "views": [{"xyz": [[x, y, z], ...],
"uv": [[u, v], ...]}, ...]} (planar views) through cv2.calibrateCameraExtended (CALIB_RATIONAL_MODEL
when "rational", k4…k6 held at 0 when "fix_k456"); prints {"cv2", "rms", "K": [fx, fy, cx, cy], "sigma": [σfx, σfy, σcx, σcy],
"dist": [...]}.

--rasterise: draws a face SVG of `cubecal rig print` (white page, black <rect>s: squares and marker
cells; the outline, the labels and the scale bar are left out) at PX_PER_MM, blurred by a Gaussian of
σ 0.8 px, as an 8-bit grey PNG. Any other shape inside the squares or markers groups is an error.
--generate: OpenCV's own image of board NAME of BOARDS.json (generateImage, or board.draw on 4.6),
PX_PER_SQUARE px a square and MARGIN_PX px of margin, blurred as above.
"""
import json
import sys

import cv2
import numpy as np

aruco = cv2.aruco
NEW_API = hasattr(aruco, "CharucoDetector")


def make_board(b):
    d = aruco.getPredefinedDictionary(getattr(aruco, b["dictionary"]))
    ids = np.array(b["ids"], dtype=np.int32)
    sx, sy = b["squares"]
    if NEW_API:
        board = aruco.CharucoBoard((sx, sy), b["square"], b["marker"], d, ids)
    else:
        board = aruco.CharucoBoard_create(sx, sy, b["square"], b["marker"], d)
        board.ids = ids
    return d, board


def detect(gray, d, board):
    if NEW_API:
        det = aruco.CharucoDetector(board)
        cc, cids, mc, mids = det.detectBoard(gray)
    else:
        mc, mids, _ = aruco.detectMarkers(gray, d, parameters=aruco.DetectorParameters_create())
        cc, cids = None, None
        if mids is not None and len(mids) > 0:
            own = set(int(i) for i in np.array(board.ids).flatten())
            keep = [k for k, i in enumerate(mids.flatten()) if int(i) in own]
            if keep:
                mc = [mc[k] for k in keep]
                mids = mids[keep]
                n, cc, cids = aruco.interpolateCornersCharuco(mc, mids, gray, board)
    return cc, cids, mc, mids


def calibrate(path):
    spec = json.load(open(path))
    obj = [np.array(v["xyz"], np.float32) for v in spec["views"]]
    img = [np.array(v["uv"], np.float32) for v in spec["views"]]
    flags = cv2.CALIB_RATIONAL_MODEL if spec.get("rational") else 0
    if spec.get("fix_k456"):
        flags |= cv2.CALIB_FIX_K4 | cv2.CALIB_FIX_K5 | cv2.CALIB_FIX_K6
    rms, k, d, _, _, sd, _, _ = cv2.calibrateCameraExtended(
        obj, img, tuple(spec["image_size"]), None, None, flags=flags
    )
    json.dump({"cv2": cv2.__version__, "rms": rms,
               "K": [k[0, 0], k[1, 1], k[0, 2], k[1, 2]],
               "sigma": [float(v) for v in sd.ravel()[:4]],
               "dist": [float(v) for v in d.ravel()]}, sys.stdout)


def rasterise(svg_path, out, px_per_mm):
    import re
    text = open(svg_path).read()
    px = float(px_per_mm)
    vb = [float(v) for v in re.search(r'viewBox="([^"]+)"', text).group(1).split()]
    img = np.full((int(round(vb[3] * px)), int(round(vb[2] * px))), 255, np.float32)
    start = text.index('<g id="squares"')
    end = text.index("<text", start) if "<text" in text[start:] else len(text)
    body = text[start:end]
    shapes = re.findall(r"<(\w+)[ >]", body)
    if set(shapes) - {"g", "rect"}:
        sys.exit(f"unexpected shapes in the board: {set(shapes) - {'g', 'rect'}}")
    # Coverage of each pixel by the black rectangles (exact area, edges anti-aliased).
    for x, y, w, h in re.findall(
        r'<rect[^>]*?x="([-\d.]+)" y="([-\d.]+)" width="([\d.]+)" height="([\d.]+)"', body
    ):
        x0, y0 = float(x) * px, float(y) * px
        x1, y1 = x0 + float(w) * px, y0 + float(h) * px
        for r in range(int(np.floor(y0)), int(np.ceil(y1))):
            cy = min(r + 1, y1) - max(r, y0)
            c0, c1 = int(np.floor(x0)), int(np.ceil(x1))
            cov = np.minimum(np.arange(c0, c1) + 1, x1) - np.maximum(np.arange(c0, c1), x0)
            img[r, c0:c1] -= 255 * cy * cov
    img = cv2.GaussianBlur(np.clip(img, 0, 255), (0, 0), 0.8)
    cv2.imwrite(out, np.round(img).astype(np.uint8))


def generate(spec_path, name, out, px_per_square, margin):
    spec = json.load(open(spec_path))
    b = [b for b in spec["boards"] if b["name"] == name][0]
    _, board = make_board(b)
    sx, sy = b["squares"]
    size = (sx * int(px_per_square) + 2 * int(margin), sy * int(px_per_square) + 2 * int(margin))
    if hasattr(board, "generateImage"):
        img = board.generateImage(size, marginSize=int(margin))
    else:
        img = board.draw(size, marginSize=int(margin))
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.8)
    cv2.imwrite(out, np.round(img).astype(np.uint8))


def main():
    if sys.argv[1] == "--calibrate":
        return calibrate(sys.argv[2])
    if sys.argv[1] == "--rasterise":
        return rasterise(*sys.argv[2:5])
    if sys.argv[1] == "--generate":
        return generate(*sys.argv[2:7])
    spec = json.load(open(sys.argv[1]))
    boards = [(b["name"], *make_board(b)) for b in spec["boards"]]
    out = {"cv2": cv2.__version__, "images": []}
    for path in sys.argv[2:]:
        gray = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if gray is None:
            sys.exit(f"cannot read {path}")
        rec = {"path": path, "markers": [], "boards": {}}
        seen = set()
        for name, d, board in boards:
            cc, cids, mc, mids = detect(gray, d, board)
            if mids is not None:
                for c, i in zip(mc, mids.flatten()):
                    if int(i) not in seen:
                        seen.add(int(i))
                        rec["markers"].append([int(i), c.reshape(4, 2).tolist()])
            corners = []
            if cids is not None and cc is not None:
                for c, i in zip(cc.reshape(-1, 2), cids.flatten()):
                    corners.append([int(i), float(c[0]), float(c[1])])
            rec["boards"][name] = corners
        out["images"].append(rec)
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
