#!/usr/bin/env python3
"""Checks the real cabinet scan's reference box against the scan's own depth.

`bench_label --cabinet` scores labels against the reference box (a
third-party measurement) projected through the captured poses. This script
asks which single box, seen through the same poses, best explains masks made
from the sensor's raw depth alone (no model): it moves the reference box
(centre, yaw about the vertical, size) to maximise their mean IoU. It then
scores other labels against both boxes. Where the depth's own box differs
from the reference, a label that follows the depth loses IoU against the
reference for being right.

Run: `nerflabel label ../shared/data/scans/cabinet --source sensor --boxes
../shared/data/scans/cabinet/boxes.json --out S` (the box to fit to), and
`nerflabel label ... --model M --out L` for the labels to score, then
`python3 dev/cabinet_box.py S L [L2 ...] [--scan DIR]`. Needs numpy, Pillow
and scipy. The fit uses every second frame at half resolution; the scores
every frame 1-57 at full resolution.
"""
import argparse
import json
import os

import numpy as np
from PIL import Image, ImageDraw
from scipy.optimize import minimize

from cabinet_edges import HEIGHT, WIDTH, convex_hull, iou


def silhouettes(scan, box, frames, scale):
    """The box's silhouette through each frame's captured pose."""
    k = np.loadtxt(os.path.join(scan, "intrinsics.txt"))[:3, :3]
    half = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)]) * box["size"]
    corners = half @ np.array(box["rotation"]).T + box["center"]
    out = []
    for frame in frames:
        world_to_camera = np.loadtxt(os.path.join(scan, "pose", f"{frame:06d}.txt"))
        cam = corners @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        uv = cam @ k.T
        uv = uv[:, :2] / uv[:, 2:] * scale
        canvas = Image.new("L", (round(WIDTH * scale), round(HEIGHT * scale)))
        ImageDraw.Draw(canvas).polygon([tuple(p) for p in convex_hull(uv)], fill=1)
        out.append(np.asarray(canvas).astype(bool))
    return out


def moved(box, p):
    """The box with its centre moved by p[0:3] m, turned by p[3] rad about z, resized by p[4:7] m."""
    c, s = np.cos(p[3]), np.sin(p[3])
    turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return {
        "center": list(np.array(box["center"]) + p[:3]),
        "size": list(np.array(box["size"]) + p[4:7]),
        "rotation": (turn @ np.array(box["rotation"])).tolist(),
    }


def masks(labels, frames, scale):
    size = (round(WIDTH * scale), round(HEIGHT * scale))
    return [np.asarray(Image.open(os.path.join(labels, "masks", f"{f:06d}.png")).resize(size, Image.NEAREST)) > 0
            for f in frames]


def mean_iou(scan, box, labels, frames, scale):
    return float(np.mean([iou(a, b) for a, b in zip(silhouettes(scan, box, frames, scale), labels)]))


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sensor", help="`nerflabel label --source sensor` output on the cabinet scan")
    ap.add_argument("labels", nargs="+", help="label outputs to score against both boxes")
    ap.add_argument("--scan", default=os.path.join(here, "../../shared/data/scans/cabinet"))
    args = ap.parse_args()

    reference = json.load(open(os.path.join(args.scan, "reference_box.json")))["boxes"][0]
    fit_frames = list(range(1, 58, 2))
    sensor = masks(args.sensor, fit_frames, 0.5)
    result = minimize(lambda p: -mean_iou(args.scan, moved(reference, p), sensor, fit_frames, 0.5),
                      np.zeros(7), method="Powell", options={"xtol": 1e-3, "ftol": 1e-5, "maxfev": 600})
    p = result.x
    depth_box = moved(reference, p)
    print(f"box of the sensor depth: centre moved {np.round(p[:3] * 1e3, 1)} mm, "
          f"turned {np.degrees(p[3]):.2f} deg, size changed {np.round(p[4:] * 1e3, 1)} mm")
    frames = list(range(1, 58))
    print("labels  IoU vs reference box  IoU vs the sensor depth's box")
    for labels in [args.sensor] + args.labels:
        m = masks(labels, frames, 1.0)
        print(f"{labels}  {mean_iou(args.scan, reference, m, frames, 1.0):.4f}  "
              f"{mean_iou(args.scan, depth_box, m, frames, 1.0):.4f}")


if __name__ == "__main__":
    main()
