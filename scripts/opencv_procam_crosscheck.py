#!/usr/bin/env python3
"""OpenCV reference for `mlsss calibrate` on the real procam-calibration set (not part of the product).

The usual OpenCV projector-camera pipeline (as in the procam-calibration scripts): OpenCV's Gray-code
decoder, findChessboardCorners on the white frame, a local homography per corner from the decoded
pixels within +-7 px (white - black > 40), calibrateCamera for the camera and for the projector, then
stereoCalibrate with the intrinsics fixed. Prints the RMS figures and intrinsics that the integration
test `calibrate_cli` compares against.

    pip install opencv-contrib-python-headless numpy
    python3 scripts/opencv_procam_crosscheck.py [../shared/data/procam-calibration/sample_data]
"""
import glob
import sys

import cv2
import numpy as np

D = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/procam-calibration/sample_data"
PW, PH = 1024, 768
HALF = 7
gc = cv2.structured_light.GrayCodePattern.create(PW, PH)
objp = np.zeros((63, 3), np.float32)
objp[:, :2] = 75 * np.mgrid[0:9, 0:7].T.reshape(-1, 2)
objs, cam, pobjs, pc, cam2 = [], [], [], [], []
for d in sorted(glob.glob(D + "/capture_*")):
    imgs = [cv2.imread(f, 0) for f in sorted(glob.glob(d + "/graycode_*.png"))]
    black = imgs.pop()
    white = imgs.pop()
    ok, c = cv2.findChessboardCorners(white, (9, 7))
    c = c.reshape(-1, 1, 2)
    objs.append(objp)
    cam.append(c)
    po, pp, cc = [], [], []
    for corner, o in zip(c, objp):
        cx, cy = int(round(corner[0][0])), int(round(corner[0][1]))
        src, dst = [], []
        for dx in range(-HALF, HALF + 1):
            for dy in range(-HALF, HALF + 1):
                x, y = cx + dx, cy + dy
                if int(white[y, x]) - int(black[y, x]) <= 40:
                    continue
                err, pix = gc.getProjPixel(imgs, x, y)
                if not err:
                    src.append((x, y))
                    dst.append(pix)
        if len(src) < HALF**2:
            continue
        h, _ = cv2.findHomography(np.array(src, np.float32), np.array(dst, np.float32))
        p = h @ np.array([corner[0][0], corner[0][1], 1])
        po.append(o)
        pp.append([p[:2] / p[2]])
        cc.append(corner)
    pobjs.append(np.array(po, np.float32))
    pc.append(np.array(pp, np.float32))
    cam2.append(np.array(cc, np.float32))
    print(d, "projector corners:", len(po))
ret, K, dist, _, _ = cv2.calibrateCamera(objs, cam, (1280, 1024), None, None)
print("camera RMS", ret, "fx fy cx cy", K[0, 0], K[1, 1], K[0, 2], K[1, 2], "dist", dist.ravel())
ret, Kp, distp, _, _ = cv2.calibrateCamera(pobjs, pc, (PW, PH), None, None)
print("projector RMS", ret, "fx fy cx cy", Kp[0, 0], Kp[1, 1], Kp[0, 2], Kp[1, 2], "dist", distp.ravel())
ret, K, dist, Kp, distp, R, T, E, F = cv2.stereoCalibrate(pobjs, cam2, pc, K, dist, Kp, distp, None)
print("stereo RMS", ret, "T", T.ravel())
print("R", R)
