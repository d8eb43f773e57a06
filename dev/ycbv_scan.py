#!/usr/bin/env python3
"""A YCB-Video slice (../shared/data/real/ycbv_video0000_first10) as a native
scan with ground truth, to check the box route against real masks.

    python3 dev/ycbv_scan.py ../shared/data/real/ycbv_video0000_first10 OUT

Writes OUT/{rgb,depth,pose}/, OUT/intrinsics.txt and OUT/gt/:
- masks/NNNNNN.png: the dataset's label images with class ids renumbered to
  box ids 1..N (order of cls_indexes);
- boxes_snug.json, boxes_loose.json: each object's box in the world frame,
  on the axes of its ground-truth 6D pose around what the frames see of it
  (the vertex map over its labelled pixels: what a user drawing on the
  point cloud would enclose), grown by 1 cm and by 2.5 cm on every side,
  so the bottom face cuts 1 / 2.5 cm into the table as a user's box does.

The camera moves about 5 mm over the ten frames: a near single view, so the
fitted model adds little beyond the sensor; the check is of the box rule
(support planes, overlap, colour snapping) on real depth and real colour.
Needs numpy, scipy and Pillow.
"""
import json
import os
import sys

import numpy as np
from PIL import Image
from scipy.io import loadmat

NAMES = {8: "gelatin_box", 14: "mug", 21: "foam_brick"}


def main(src, out):
    stems = sorted(f[:6] for f in os.listdir(src) if f.endswith("-color.png"))
    if not stems:
        sys.exit(f"{src}: no NNNNNN-color.png frames")
    for d in ("rgb", "depth", "pose", "gt/masks"):
        os.makedirs(os.path.join(out, d), exist_ok=True)
    classes, object_in_world, lo, hi = None, {}, {}, {}
    for stem in stems:
        meta = loadmat(os.path.join(src, f"{stem}-meta.mat"))
        cls = [int(c) for c in meta["cls_indexes"].ravel()]
        classes = classes or cls
        world_to_camera = np.eye(4)
        world_to_camera[:3] = meta["rotation_translation_matrix"]
        camera_to_world = np.linalg.inv(world_to_camera)
        k = meta["intrinsic_matrix"]
        factor = float(meta["factor_depth"].ravel()[0])
        Image.open(os.path.join(src, f"{stem}-color.png")).convert("RGB").save(os.path.join(out, "rgb", f"{stem}.png"))
        depth = np.array(Image.open(os.path.join(src, f"{stem}-depth.png"))).astype(np.float64)
        mm = np.round(depth / factor * 1000.0).astype(np.uint16)
        Image.fromarray(mm).save(os.path.join(out, "depth", f"{stem}.png"))
        np.savetxt(os.path.join(out, "pose", f"{stem}.txt"), world_to_camera)
        label = np.array(Image.open(os.path.join(src, f"{stem}-label.png")))
        ids = np.zeros(label.shape, np.uint16)
        vertmap = meta["vertmap"]
        for i, c in enumerate(cls):
            if c not in classes:
                sys.exit(f"{stem}: class {c} not in the first frame")
            box_id = classes.index(c) + 1
            ids[label == c] = box_id
            pose = np.eye(4)
            pose[:3] = meta["poses"][:, :, i]
            object_in_world.setdefault(c, camera_to_world @ pose)
            v = vertmap[label == c]
            v = v[np.isfinite(v).all(axis=1) & (np.abs(v).sum(axis=1) > 0)]
            if len(v):
                lo[c] = np.minimum(lo.get(c, v.min(axis=0)), v.min(axis=0))
                hi[c] = np.maximum(hi.get(c, v.max(axis=0)), v.max(axis=0))
        Image.fromarray(ids).save(os.path.join(out, "gt", "masks", f"{stem}.png"))
    np.savetxt(os.path.join(out, "intrinsics.txt"), k)
    for name, margin in (("boxes_snug.json", 0.01), ("boxes_loose.json", 0.025)):
        boxes = []
        for c in classes:
            m = object_in_world[c]
            middle = m[:3, :3] @ ((lo[c] + hi[c]) / 2.0) + m[:3, 3]
            boxes.append({
                "label": NAMES.get(c, f"class_{c}"),
                "center": middle.tolist(),
                "size": (hi[c] - lo[c] + 2.0 * margin).tolist(),
                "rotation": m[:3, :3].tolist(),
            })
        with open(os.path.join(out, "gt", name), "w") as f:
            json.dump({"boxes": boxes}, f, indent=1)
    print(f"{len(stems)} frames, objects {[NAMES.get(c, c) for c in classes]} -> {out}")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
