"""Load a merged nerflabel dataset the way ML code does; print one line per
library: `ok <lib> ...` or `skip <lib>: <why>`. Asserts on what it reads.

Usage: python3 check_merged.py OUT ID [ID ...]   (the ids of the finished scans)
"""
import json
import os
import sys

out, ids = sys.argv[1], sorted(sys.argv[2:])
synth = os.path.join(out, "synth")
files = sorted(
    os.path.join(synth, d, "part-0.parquet") for d in os.listdir(synth) if d.startswith("scan=")
)

try:
    import pyarrow.dataset as pads
except ImportError as e:
    print(f"skip pyarrow: {e}")
else:
    table = pads.dataset(synth, format="parquet", partitioning="hive").to_table()
    scans = sorted(set(table.column("scan").to_pylist()))
    assert scans == ids, (scans, ids)
    assert table.num_rows > 0
    print(f"ok pyarrow {table.num_rows} rows, scans {scans}")

try:
    import polars as pl
except ImportError as e:
    print(f"skip polars: {e}")
else:
    df = pl.scan_parquet(os.path.join(synth, "**", "*.parquet"), hive_partitioning=True).collect()
    scans = sorted(df["scan"].unique().to_list())
    assert scans == ids, (scans, ids)
    print(f"ok polars {df.height} rows, scans {scans}")

try:
    import datasets
except ImportError as e:
    print(f"skip datasets: {e}")
else:
    ds = datasets.Dataset.from_parquet(files)
    assert sorted(set(ds["scan"])) == ids
    images = [k for k, f in ds.features.items() if type(f).__name__ == "Image"]
    for name in images:
        image = ds[0][name]
        assert image.size[0] > 0 and image.size[1] > 0, name
    print(f"ok datasets {ds.num_rows} rows, image columns {images}")

for split in ("train", "val"):
    with open(os.path.join(out, "coco", f"{split}.json")) as f:
        coco = json.load(f)
    for image in coco["images"]:
        assert os.path.isfile(os.path.join(out, image["file_name"])), image["file_name"]
print("ok coco paths resolve from OUT")
