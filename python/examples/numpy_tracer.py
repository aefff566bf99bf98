"""A small wavefront path tracer in numpy that records every ray it traces through rtvtk.

A box with a ceiling light and a block inside; per pixel sample: the camera ray, at each diffuse
hit a shadow ray towards a random point of the light and a cosine-sampled bounce (two bounces at
most). Whole wavefronts go to ``Recorder.add_rays``, as a Dr.Jit or numpy renderer would hand
them over. Run it: ``python examples/numpy_tracer.py OUT_DIR``; then ``rtvtk view OUT_DIR``.
"""

from __future__ import annotations

import sys
import time
from typing import Dict, Tuple, Union

import numpy as np

import rtvtk


def _quad(a, b, c, d):
    return [(a, b, c), (a, c, d)]


def box_scene() -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list]:
    """Triangles (n, 3, 3), material per triangle, per material colour and emission, names."""
    tris, mats = [], []

    def add(quads, m):
        for q in quads:
            for t in _quad(*q):
                tris.append(t)
                mats.append(m)

    p = lambda x, y, z: (x, y, z)  # noqa: E731
    add([(p(0, 0, 0), p(1, 0, 0), p(1, 0, 1), p(0, 0, 1))], 0)  # floor
    add([(p(0, 1, 0), p(0, 1, 1), p(1, 1, 1), p(1, 1, 0))], 0)  # ceiling
    add([(p(0, 0, 1), p(1, 0, 1), p(1, 1, 1), p(0, 1, 1))], 0)  # back
    add([(p(0, 0, 0), p(0, 0, 1), p(0, 1, 1), p(0, 1, 0))], 1)  # left, red
    add([(p(1, 0, 0), p(1, 1, 0), p(1, 1, 1), p(1, 0, 1))], 2)  # right, green
    # The light, just below the ceiling, facing down.
    add([(p(0.35, 0.999, 0.35), p(0.65, 0.999, 0.35), p(0.65, 0.999, 0.65), p(0.35, 0.999, 0.65))], 3)
    # A block.
    lo, hi, h = 0.25, 0.55, 0.4
    add([(p(lo, h, lo), p(hi, h, lo), p(hi, h, hi), p(lo, h, hi))], 0)
    add([(p(lo, 0, lo), p(hi, 0, lo), p(hi, h, lo), p(lo, h, lo))], 0)
    add([(p(hi, 0, lo), p(hi, 0, hi), p(hi, h, hi), p(hi, h, lo))], 0)
    add([(p(lo, 0, hi), p(lo, h, hi), p(hi, h, hi), p(hi, 0, hi))], 0)
    add([(p(lo, 0, lo), p(lo, h, lo), p(lo, h, hi), p(lo, 0, hi))], 0)
    colors = np.array([[0.73, 0.73, 0.73], [0.63, 0.06, 0.05], [0.12, 0.45, 0.15], [0.78, 0.78, 0.78]], np.float32)
    emission = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [15, 13, 9]], np.float32)
    return np.array(tris, np.float32), np.array(mats, np.uint32), colors, emission, ["white", "red", "green", "light"]


def intersect(o: np.ndarray, d: np.ndarray, tris: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Closest hit of each ray (Möller–Trumbore over every triangle): t (inf: miss), triangle."""
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    pv = np.cross(d[:, None, :], e2[None])
    det = np.einsum("rtk,tk->rt", pv, e1)
    inv = np.where(np.abs(det) > 1e-12, 1.0 / np.where(det == 0, 1, det), 0.0)
    tv = o[:, None, :] - v0[None]
    u = np.einsum("rtk,rtk->rt", tv, pv) * inv
    qv = np.cross(tv, e1[None])
    v = np.einsum("rk,rtk->rt", d, qv) * inv
    t = np.einsum("tk,rtk->rt", e2, qv) * inv
    ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-4)
    t = np.where(ok, t, np.inf)
    prim = np.argmin(t, axis=1)
    return t[np.arange(len(o)), prim], prim


def camera_rays(width: int, height: int, spp: int, rng: np.random.Generator):
    pos, target, up, fov = np.array([0.5, 0.5, -1.35]), np.array([0.5, 0.5, 0.5]), np.array([0, 1.0, 0]), 40.0
    f = (target - pos) / np.linalg.norm(target - pos)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    y, x, s = np.meshgrid(np.arange(height), np.arange(width), np.arange(spp), indexing="ij")
    x, y, s = x.ravel(), y.ravel(), s.ravel()
    px, py = x + rng.random(x.size), y + rng.random(y.size)
    k = np.tan(np.radians(fov) / 2)
    sx = (2 * px / width - 1) * k * width / height
    sy = (1 - 2 * py / height) * k
    d = f[None] + sx[:, None] * r[None] + sy[:, None] * u[None]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.repeat(pos[None], len(d), 0), d, np.stack([x, y], 1), s, (pos, target, up, fov)


def normals(tris: np.ndarray) -> np.ndarray:
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def trace(out: Union[str, rtvtk.Recorder], width: int = 32, height: int = 32, spp: int = 2, seed: int = 0) -> Dict[str, float]:
    """Renders and records into the dataset directory ``out`` (or into a recorder, such as an
    immediate-mode one, which is left open); returns ray counts and the seconds spent tracing
    and recording."""
    rng = np.random.default_rng(seed)
    tris, mats, colors, emission, names = box_scene()
    tn = normals(tris)
    light = np.where(emission[mats].sum(1) > 0)[0]
    o, d, pixel, sample, cam = camera_rays(width, height, spp, rng)
    n_paths = len(o)
    # Per path, its rays in order: (parent index within the path, o, d, t, kind, prim, throughput).
    paths = [[] for _ in range(n_paths)]
    throughput = np.ones((n_paths, 3), np.float32)
    t_trace = time.perf_counter()
    cur_o, cur_d, parent_of = o, d, np.full(n_paths, -1)
    alive = np.arange(n_paths)
    kind = "camera"
    image = np.zeros((n_paths, 3))
    for depth in range(3):
        t, prim = intersect(cur_o, cur_d, tris)
        hit = np.isfinite(t)
        for j, p in enumerate(alive):
            paths[p].append((int(parent_of[j]), cur_o[j], cur_d[j], float(t[j]) if hit[j] else float("nan"), kind, int(prim[j]) if hit[j] else -1, throughput[p].copy()))
        me = np.array([len(paths[p]) - 1 for p in alive])
        m = mats[prim]
        image[alive[hit & (emission[m].sum(1) > 0)]] += (throughput[alive] * emission[m])[hit & (emission[m].sum(1) > 0)]
        diffuse = hit & (emission[m].sum(1) == 0)
        if depth == 2 or not diffuse.any():
            break
        alive, me, t, prim = alive[diffuse], me[diffuse], t[diffuse], prim[diffuse]
        x = cur_o[diffuse] + t[:, None] * cur_d[diffuse]
        n = tn[prim]
        n = np.where((np.einsum("rk,rk->r", n, cur_d[diffuse]) > 0)[:, None], -n, n)
        throughput[alive] *= colors[mats[prim]]
        # Shadow rays towards a random point of the light (next-event estimation).
        lt = tris[rng.choice(light, len(alive))]
        a, b = rng.random(len(alive)), rng.random(len(alive))
        flip = a + b > 1
        a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
        lp = lt[:, 0] + a[:, None] * (lt[:, 1] - lt[:, 0]) + b[:, None] * (lt[:, 2] - lt[:, 0])
        # From the offset origin: a direction taken from the unoffset hit point misses the light
        # by the offset at grazing angles (the paper's wrong-shadow query finds those rays).
        so = x + n * 1e-4
        sd = lp - so
        sd /= np.linalg.norm(sd, axis=1, keepdims=True)
        st, sp = intersect(so, sd, tris)
        for j, p in enumerate(alive):
            paths[p].append((int(me[j]), so[j], sd[j], float(st[j]) if np.isfinite(st[j]) else float("nan"), "shadow", int(sp[j]) if np.isfinite(st[j]) else -1, throughput[p].copy()))
        # Cosine-weighted bounce.
        u1, u2 = rng.random(len(alive)), rng.random(len(alive))
        rr, phi = np.sqrt(u1), 2 * np.pi * u2
        tx = np.cross(n, np.where(np.abs(n[:, :1]) > 0.9, [[0, 1.0, 0]], [[1.0, 0, 0]]))
        tx /= np.linalg.norm(tx, axis=1, keepdims=True)
        ty = np.cross(n, tx)
        cur_d = (rr * np.cos(phi))[:, None] * tx + (rr * np.sin(phi))[:, None] * ty + np.sqrt(1 - u1)[:, None] * n
        cur_o, parent_of, kind = x + n * 1e-4, me, "diffuse"
    traced = time.perf_counter() - t_trace
    # One wavefront call: every path is a tree.
    t_rec = time.perf_counter()
    own = not isinstance(out, rtvtk.Recorder)
    rec = rtvtk.Recorder(out, payload={"throughput": "f32x3"}) if own else out
    rec.set_scene(tris, mats, colors, emission, names)
    pos, target, up, fov = cam
    rec.set_camera(pos, target, up, fov, width, height)
    flat = [(i, r) for i, rays in enumerate(paths) for r in rays]
    ids = rec.add_rays(
        tree=np.array([i for i, _ in flat]),
        parent=np.array([r[0] for _, r in flat]),
        origin=np.array([r[1] for _, r in flat]),
        direction=np.array([r[2] for _, r in flat]),
        t=np.array([r[3] for _, r in flat]),
        kind=[r[4] for _, r in flat],
        pixel=pixel[[i for i, _ in flat]],
        sample=sample[[i for i, _ in flat]],
        prim=np.array([r[5] for _, r in flat]),
        throughput=np.array([r[6] for _, r in flat], np.float32),
    )
    summary = rec.finish() if own else {"rays": len(flat), "trees": len(ids)}
    recorded = time.perf_counter() - t_rec
    kinds = [r[4] for rays in paths for r in rays]
    return {
        "rays": summary["rays"],
        "trees": summary["trees"],
        "camera": kinds.count("camera"),
        "shadow": kinds.count("shadow"),
        "diffuse": kinds.count("diffuse"),
        "trace_seconds": traced,
        "record_seconds": recorded,
        "mean_radiance": float(image.mean()),
    }


if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "numpy-trace"
    stats = trace(out, 48, 48, 4)
    print(stats)
    s = rtvtk.open(out)
    print(s.sql("SELECT kind, depth, count(*) AS rays FROM rays GROUP BY kind, depth ORDER BY kind, depth").to_pandas())
    s.render(layers=["geometry", "composition", "rays"], pixel=(24, 30), size=(480, 480)).save(f"{out}/rays.png")
    print(f"wrote {out}/rays.png")
