"""OpenCV findChessboardCornersSB on the bailus_tsai inside-corner photos: which pattern sizes it finds, and
whether a found grid stays on one wall (a grid across the fold is not a planar board).
usage: /usr/bin/python3 sb_bailus.py"""
import cv2, numpy as np
D = "../shared/datasets/bailus_tsai_cube_stereo/images/"
for name in ("3D_L0933.JPG", "3D_R0548.JPG"):
    g = cv2.imread(D + name, cv2.IMREAD_GRAYSCALE)
    found = []
    for size in [(5, 5), (7, 5), (7, 7), (9, 7), (7, 9), (9, 9)]:
        ok, c, meta = cv2.findChessboardCornersSBWithMeta(g, size, cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_LARGER)
        if ok:
            s = c.reshape(-1, 2)
            found.append(f"{size}: {len(s)} corners (meta {meta.shape}), u {s[:,0].min():.0f}..{s[:,0].max():.0f}")
        else:
            found.append(f"{size}: -")
    print(name); [print("   ", f) for f in found]
