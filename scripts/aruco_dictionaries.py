#!/usr/bin/env python3
"""Write data/aruco_dictionaries.txt: OpenCV's predefined ArUco dictionaries 4x4, 5x5 and 6x6.

OpenCV (Apache-2.0) defines them in modules/objdetect/src/aruco/predefined_dictionaries.hpp; this
script reads them through cv2 (cv2.aruco.getPredefinedDictionary(...).bytesList) and writes one line
per marker: the marker's bits in rotation 0, row-major from the top-left bit, as a hex number whose
most significant of the n*n bits is the first (bit value 1 = white cell). The _50, _100 and _250
dictionaries of a size are the first ids of the _1000 one (checked here), so only the _1000 tables are
written, each with every predefined dictionary's maxCorrectionBits.

Usage: python3 scripts/aruco_dictionaries.py > data/aruco_dictionaries.txt
(tests/charuco_opencv.rs checks the file against the installed cv2 bit by bit.)
"""
import sys

import cv2
import numpy as np

aruco = cv2.aruco


def bits(d, i):
    b = aruco.Dictionary.getBitsFromByteList(d.bytesList[i : i + 1], d.markerSize)
    return b.astype(np.uint8)


def main():
    out = sys.stdout
    out.write("# OpenCV predefined ArUco dictionaries, written by scripts/aruco_dictionaries.py\n")
    out.write(f"# from cv2 {cv2.__version__} (OpenCV, Apache-2.0); see that script for the format.\n")
    for n in (4, 5, 6):
        big = aruco.getPredefinedDictionary(getattr(aruco, f"DICT_{n}X{n}_1000"))
        corrections = []
        for count in (50, 100, 250, 1000):
            d = aruco.getPredefinedDictionary(getattr(aruco, f"DICT_{n}X{n}_{count}"))
            assert d.markerSize == n and d.bytesList.shape[0] == count
            assert (d.bytesList == big.bytesList[:count]).all(), f"{n}x{n}_{count} is not a prefix"
            corrections.append(f"{count}:{d.maxCorrectionBits}")
        out.write(f"dictionary {n} {' '.join(corrections)}\n")
        for i in range(1000):
            b = bits(big, i).flatten()
            code = 0
            for v in b:
                code = (code << 1) | int(v)
            out.write(f"{code:x}\n")


if __name__ == "__main__":
    main()
