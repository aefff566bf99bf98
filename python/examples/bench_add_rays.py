"""`Recorder.add_rays` against pyarrow writing the same arrays to a zstd Parquet file, in one run.

Both get the same n rays (trees of 4: a camera ray, a shadow, a diffuse bounce and its shadow,
with an f32x3 throughput each); the recorder's time includes `finish` (sealed, crash-safe), the
baseline's `pq.write_table` to a file. Prints Mrays/s of each and the ratio (goal: >= 1.0x).
Run from a release build of the package (`pip install ./python`): `python bench_add_rays.py [N]`.
"""

import sys
import tempfile
import time

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import rtvtk


def arrays(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    tree = np.repeat(np.arange(n // 4, dtype=np.int64), 4)[:n]
    parent = np.tile(np.array([-1, 0, 0, 2], np.int32), n // 4 + 1)[:n]
    origin = rng.random((n, 3), np.float32) * 500
    direction = rng.normal(size=(n, 3)).astype(np.float32)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    t = rng.random(n, np.float32) * 800
    codes = np.tile(np.array([0, 1, 2, 1], np.uint8), n // 4 + 1)[:n]
    pixel = np.stack([tree % 512, tree // 512 % 512], 1).astype(np.uint32)
    throughput = rng.random((n, 3), np.float32)
    return tree, parent, origin, direction, t, codes, pixel, throughput


def main(n: int) -> None:
    tree, parent, origin, direction, t, codes, pixel, throughput = arrays(n)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        rec = rtvtk.Recorder(f"{d}/trace", payload={"throughput": "f32x3"})
        rec.add_rays(tree, parent, origin, direction, t, (codes, ["camera", "shadow", "diffuse"]), pixel, throughput=throughput)
        rec.finish()
        ours = time.perf_counter() - t0
        t0 = time.perf_counter()
        table = pa.table(
            {
                "tree_id": tree, "parent": parent,
                "origin_x": origin[:, 0], "origin_y": origin[:, 1], "origin_z": origin[:, 2],
                "dir_x": direction[:, 0], "dir_y": direction[:, 1], "dir_z": direction[:, 2],
                "t": t, "kind": codes, "pixel_x": pixel[:, 0], "pixel_y": pixel[:, 1],
                "throughput": pa.FixedSizeListArray.from_arrays(throughput.ravel(), 3),
            }
        )
        pq.write_table(table, f"{d}/plain.parquet", compression="zstd")
        base = time.perf_counter() - t0
    print(f"{n} rays: rtvtk add_rays + finish {n / ours / 1e6:.2f} Mrays/s, pyarrow zstd Parquet {n / base / 1e6:.2f} Mrays/s, ratio {base / ours:.2f}x")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2_000_000)
