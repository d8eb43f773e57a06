#!/usr/bin/env python3
"""Checks the real cabinet scan's reference silhouettes against its images.

The cabinet benchmark (`bench_label --cabinet`) scores labels against the
reference box projected through the captured poses. Where a captured pose is
off, that silhouette misses the cabinet in the image, and a label that sits on
the image's edges loses IoU for being right. This script measures it:

- for every frame 1-57, the reference box's silhouette through the captured
  pose, and the same silhouette shifted (up to --search px) to where its
  contour lies on the strongest colour edges of the frame;
- the mean colour gradient along each contour (the label's, the reference's,
  the shifted reference's): a contour on the cabinet's outline scores high;
- the labels' IoU against both references.

Run: `nerflabel label ../shared/data/scans/cabinet --model M --out L`, then
`python3 dev/cabinet_edges.py L [--scan DIR] [--search 8]`. Needs numpy and Pillow.
"""
import argparse
import json
import os

import numpy as np
from PIL import Image, ImageDraw, ImageFilter

WIDTH, HEIGHT = 640, 480


def convex_hull(points):
    """Monotone-chain hull of 2D points, counter-clockwise."""
    pts = sorted(map(tuple, points))

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def contour(mask):
    """Mask pixels with a 4-neighbour outside the mask."""
    inner = np.zeros_like(mask)
    inner[1:-1, 1:-1] = mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:]
    edge = mask & ~inner
    edge[[0, -1], :] = False
    edge[:, [0, -1]] = False
    return edge


def shifted(mask, dx, dy):
    out = np.zeros_like(mask)
    h, w = mask.shape
    out[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] = \
        mask[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
    return out


def iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def gradient(path):
    """Colour-edge strength: central differences of the lightly blurred grey image."""
    grey = Image.open(path).convert("L").filter(ImageFilter.GaussianBlur(1))
    g = np.asarray(grey).astype(float)
    gx = np.zeros_like(g)
    gy = np.zeros_like(g)
    gx[:, 1:-1] = g[:, 2:] - g[:, :-2]
    gy[1:-1] = g[2:] - g[:-2]
    return np.hypot(gx, gy)


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("labels", help="output folder of `nerflabel label` on the cabinet scan")
    ap.add_argument("--scan", default=os.path.join(here, "../../shared/data/scans/cabinet"))
    ap.add_argument("--search", type=int, default=8, help="largest shift tried, pixels")
    args = ap.parse_args()

    k = np.loadtxt(os.path.join(args.scan, "intrinsics.txt"))[:3, :3]
    box = json.load(open(os.path.join(args.scan, "reference_box.json")))["boxes"][0]
    half = np.array([[x, y, z] for x in (-.5, .5) for y in (-.5, .5) for z in (-.5, .5)]) * box["size"]
    corners = half @ np.array(box["rotation"]).T + box["center"]

    rows = []
    for frame in range(1, 58):
        world_to_camera = np.loadtxt(os.path.join(args.scan, "pose", f"{frame:06d}.txt"))
        cam = corners @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        uv = cam @ k.T
        uv = uv[:, :2] / uv[:, 2:]
        canvas = Image.new("L", (WIDTH, HEIGHT))
        ImageDraw.Draw(canvas).polygon([tuple(p) for p in convex_hull(uv)], fill=1)
        reference = np.asarray(canvas).astype(bool)
        label = np.asarray(Image.open(os.path.join(args.labels, "masks", f"{frame:06d}.png"))) > 0
        strength = gradient(os.path.join(args.scan, "rgb", f"{frame:06d}.jpg"))

        ys, xs = np.nonzero(contour(reference))
        best = (strength[ys, xs].mean(), 0, 0)
        for dy in range(-args.search, args.search + 1):
            for dx in range(-args.search, args.search + 1):
                y, x = ys + dy, xs + dx
                inside = (y >= 0) & (y < HEIGHT) & (x >= 0) & (x < WIDTH)
                if inside.any():
                    best = max(best, (strength[y[inside], x[inside]].mean(), dx, dy))
        aligned = shifted(reference, best[1], best[2])
        rows.append((frame, iou(label, reference), iou(label, aligned), np.hypot(best[1], best[2]),
                     strength[contour(label)].mean(), strength[ys, xs].mean(), best[0]))

    print("frame  IoU vs reference  IoU vs edge-aligned  shift px  edge strength: label / reference / aligned")
    for r in rows:
        print(f"{r[0]:5d}  {r[1]:16.4f}  {r[2]:19.4f}  {r[3]:8.1f}  {r[4]:6.1f} / {r[5]:6.1f} / {r[6]:6.1f}")
    a = np.array([r[1:] for r in rows])
    print(f"mean   {a[:, 0].mean():16.4f}  {a[:, 1].mean():19.4f}  {np.median(a[:, 2]):8.1f}  "
          f"{a[:, 3].mean():6.1f} / {a[:, 4].mean():6.1f} / {a[:, 5].mean():6.1f}   (shift: median)")


if __name__ == "__main__":
    main()
