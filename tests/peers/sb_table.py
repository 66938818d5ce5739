"""OpenCV findChessboardCornersSB vs cubecal detect on the real image sets (issue 19, line 3 table).
usage: /usr/bin/python3 sb_table.py OURS_JSON IMAGE... (pattern 9x6)"""
import sys, json, cv2, numpy as np
ours = {f["image"].split("/")[-1]: f for f in json.load(open(sys.argv[1]))}
rows = []
for path in sys.argv[2:]:
    g = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    ok, c = cv2.findChessboardCornersSB(g, (9, 6), flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    okc, cc = cv2.findChessboardCorners(g, (9, 6))
    f = ours.get(path.split("/")[-1], {"faces": []})
    pts = [c2["uv"] for face in f["faces"] for c2 in face["corners"]]
    dist = ""
    if ok and pts:
        p = np.array(pts); s = c.reshape(-1, 2)
        d = [np.min(np.linalg.norm(p - q, axis=1)) for q in s]
        dist = f"{np.sqrt(np.mean(np.square(d))):.3f}"
    rows.append((path.split("/")[-1], ok, len(c) if ok else 0, okc, len(f["faces"]), len(pts), dist))
print("| image | SB found | SB corners | classic found | cubecal faces | cubecal corners | RMS SB↔cubecal px |")
print("|---|---|---|---|---|---|---|")
for r in rows: print("| " + " | ".join(str(x) for x in r) + " |")
print(f"SB found {sum(r[1] for r in rows)}/{len(rows)}, classic {sum(bool(r[3]) for r in rows)}/{len(rows)}, cubecal {sum(r[4]>0 for r in rows)}/{len(rows)}")
