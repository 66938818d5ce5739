"""Same solver (cv2.calibrateCamera, 5-parameter Brown) fed by three detectors' corners, per camera of the
OpenCV stereo sample set: reprojection RMS shows the detectors' corner noise; fx/cx vs Bouguet's reference.
usage: /usr/bin/python3 sb_calib.py OURS_JSON"""
import sys, json, glob, cv2, numpy as np
ours = {f["image"].split("/")[-1]: f for f in json.load(open(sys.argv[1]))}
ref = {"left": (533.00371, 341.58612, 234.25940), "right": (536.98262, 326.47209, 249.33257)}
obj = np.array([[c * 30.0, r * 30.0, 0] for r in range(6) for c in range(9)], np.float32)
crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
print("| camera | detector | views | reproj RMS px | fx (ref) | cx | cy |")
print("|---|---|---|---|---|---|---|")
for cam in ("left", "right"):
    paths = sorted(glob.glob(f"../shared/datasets/opencv_stereo_left_right/images/{cam}*.jpg"))
    for det in ("findChessboardCornersSB", "findChessboardCorners+cornerSubPix", "cubecal"):
        O, I = [], []
        for p in paths:
            g = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
            if det == "cubecal":
                f = ours[p.split("/")[-1]]["faces"]
                if not f: continue
                cs = f[0]["corners"]
                if len(cs) != 54: continue
                O.append(np.array([c["xyz"] for c in cs], np.float32)); I.append(np.array([c["uv"] for c in cs], np.float32)); continue
            if det.startswith("findChessboardCornersSB"):
                ok, c = cv2.findChessboardCornersSB(g, (9, 6), flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
            else:
                ok, c = cv2.findChessboardCorners(g, (9, 6))
                if ok: c = cv2.cornerSubPix(g, c, (5, 5), (-1, -1), crit)
            if ok: O.append(obj); I.append(c.reshape(-1, 2).astype(np.float32))
        rms, K, dist, _, _ = cv2.calibrateCamera(O, I, (640, 480), None, None)
        fx, cx, cy = ref[cam]
        print(f"| {cam} | {det} | {len(O)}/{len(paths)} | {rms:.4f} | {K[0,0]:.2f} ({(K[0,0]/fx-1)*100:+.2f} %) | {K[0,2]:.2f} ({cx}) | {K[1,2]:.2f} ({cy}) |")
