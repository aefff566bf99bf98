"""Record Mitsuba 3's path tracer: every ray it traces, into an rtvtk dataset.

``rtvtk.mitsuba.record(scene, out, spp=..., max_depth=...)`` renders a Mitsuba 3 scene (an XML
file, a scene dictionary, a loaded ``mi.Scene``, or ``"cornell"`` for ``mi.cornell_box()``) with
Mitsuba's ``path`` integrator written out in Python over Mitsuba's scalar API — the same
estimator as the built-in one (unidirectional path tracing, next-event estimation with multiple
importance sampling by the power heuristic, Russian roulette from ``rr_depth``) — and records:

- camera rays, each bounce's continuation ray (kind by the sampled BSDF lobe: ``diffuse``,
  ``glossy``, ``specular`` for delta reflection, ``transmission``), and the shadow ray of every
  emitter sample (``shadow``), with hit distance and primitive (a shadow ray that reaches an
  area light ends on it, as rtvtk's tracers record theirs);
- per ray the payload ``throughput`` (the path's weight before the ray) and ``radiance`` (what
  the ray adds to its pixel: emission it hits, weighted, or its emitter sample's contribution),
  so ``sum(radiance) / spp`` per pixel is the image;
- Mitsuba's geometry (each mesh's triangles in world space, its BSDF's reflectance and its
  area emitter's radiance), so the emissive triangles and the point emitters become the
  ``lights`` table, its camera (``to_world``, field of view, film size) as the dataset's camera,
  and its picture.

Mitsuba is an optional dependency: ``pip install ./python[mitsuba]``. The scalar variant
(``scalar_rgb``) is selected when no variant is set.
"""

from __future__ import annotations

import math
import os
import sys
import time
from typing import Any, Dict, List, Optional, Tuple, Union

import numpy as np

from . import RecordError, Recorder

PathLike = Union[str, "os.PathLike[str]"]

#: Ray kinds the recording uses (``glossy`` is registered beside rtvtk's built-in kinds).
KINDS = ("camera", "shadow", "diffuse", "glossy", "specular", "transmission")


def _mitsuba() -> Any:
    try:
        import mitsuba as mi
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise RecordError("rtvtk.mitsuba needs Mitsuba 3: pip install ./python[mitsuba] (or pip install mitsuba)") from e
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    if not mi.variant().startswith("scalar_"):
        raise RecordError(f"rtvtk.mitsuba records with a scalar variant (scalar_rgb); Mitsuba is set to {mi.variant()}")
    return mi


def load(scene: Any, size: Optional[Tuple[int, int]] = None, box_filter: bool = True) -> Any:
    """A Mitsuba scene from ``scene``: ``"cornell"``, an XML path, a dictionary or an
    ``mi.Scene`` (used as it is). ``size`` sets the film's width and height, and the film's
    reconstruction filter is a box (one pixel's samples make that pixel) unless
    ``box_filter=False``: what ``record`` estimates per pixel. Dictionaries and ``"cornell"``
    take both; an XML file takes them as the parameters ``resx``, ``resy`` and ``rfilter`` when
    it declares them (``<default name="resx" .../>``)."""
    mi = _mitsuba()
    if isinstance(scene, mi.Scene):
        return scene
    if isinstance(scene, str) and scene == "cornell":
        scene = mi.cornell_box()
    if isinstance(scene, dict):
        d = dict(scene)
        sensor = dict(next(v for v in d.values() if isinstance(v, dict) and v.get("type") in ("perspective", "thinlens")))
        key = next(k for k, v in d.items() if isinstance(v, dict) and v.get("type") in ("perspective", "thinlens"))
        film = dict(sensor.get("film", {"type": "hdrfilm"}))
        if size is not None:
            film["width"], film["height"] = int(size[0]), int(size[1])
        if box_filter:
            film["rfilter"] = {"type": "box"}
        sensor["film"] = film
        d[key] = sensor
        return mi.load_dict(d)
    path = os.fspath(scene)
    if not os.path.exists(path):
        raise RecordError(f"{path}: no such Mitsuba scene file")
    params: Dict[str, Any] = {}
    if size is not None:
        params["resx"], params["resy"] = int(size[0]), int(size[1])
    if box_filter:
        params["rfilter"] = "box"
    try:
        return mi.load_file(path, **params)
    except Exception as e:
        if params:
            try:
                return mi.load_file(path)
            except Exception:
                pass
        raise RecordError(f"{path}: Mitsuba could not load it: {e}") from e


def _rgb(value: Any) -> List[float]:
    v = np.asarray(value, dtype=np.float64).ravel()
    if v.size == 1:
        v = np.repeat(v, 3)
    return [float(x) for x in v[:3]]


def _geometry(mi: Any, scene: Any) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, List[str], List[int], List[str]]:
    """Every mesh's triangles (world space) with one material per shape: vertices (n, 3, 3),
    material per triangle, colours, emission, names; the first triangle of each shape (its
    primitives are numbered from there), and the shapes that are not meshes (not drawn)."""
    tris, mats, colors, emission, names, offsets, skipped = [], [], [], [], [], [], []
    count = 0
    for i, sh in enumerate(scene.shapes()):
        offsets.append(count)
        if not sh.is_mesh():
            skipped.append(f"{type(sh).__name__} {sh.id()!r}")
            continue
        p = np.asarray(sh.vertex_positions_buffer(), dtype=np.float32).reshape(-1, 3)
        f = np.asarray(sh.faces_buffer(), dtype=np.int64).reshape(-1, 3)
        tris.append(p[f])
        mats.append(np.full(len(f), len(names), np.uint32))
        count += len(f)
        colour = [0.5, 0.5, 0.5]
        bsdf = sh.bsdf()
        if bsdf is not None:
            params = mi.traverse(bsdf)
            for key in ("reflectance.value", "diffuse_reflectance.value", "base_color.value", "specular_reflectance.value"):
                if key in params:
                    colour = _rgb(params[key])
                    break
        glow = [0.0, 0.0, 0.0]
        if sh.emitter() is not None:
            params = mi.traverse(sh.emitter())
            if "radiance.value" in params:
                glow = _rgb(params["radiance.value"])
        colors.append(colour)
        emission.append(glow)
        # Mitsuba merges shapes of one BSDF into one unnamed mesh: name it after the BSDF.
        names.append(sh.id() or (bsdf.id() if bsdf is not None else "") or f"shape{i}")
    if not tris:
        raise RecordError("the Mitsuba scene has no triangle mesh to record")
    return (
        np.concatenate(tris).astype(np.float32),
        np.concatenate(mats),
        np.asarray(colors, np.float32),
        np.asarray(emission, np.float32),
        names,
        offsets,
        skipped,
    )


def _point_lights(mi: Any, scene: Any) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """Mitsuba's point emitters: positions and intensities (k, 3), or None without any."""
    positions, intensities = [], []
    for e in scene.emitters():
        params = mi.traverse(e)
        if mi.has_flag(e.flags(), mi.EmitterFlags.DeltaPosition) and "position" in params:
            positions.append(_rgb(params["position"]))
            intensities.append(_rgb(params["intensity.value"]) if "intensity.value" in params else [1.0, 1.0, 1.0])
    if not positions:
        return None
    return np.asarray(positions, np.float32), np.asarray(intensities, np.float32)


def _camera(mi: Any, sensor: Any) -> Tuple[List[float], List[float], List[float], float, int, int]:
    """The sensor as rtvtk's camera: position, target, up, vertical field of view (degrees),
    film size. Mitsuba's camera looks along its local +z with +y up (and +x to the left: the
    same picture as rtvtk's right = forward x up)."""
    m = np.asarray(sensor.world_transform().matrix, dtype=np.float64)
    pos = m[:3, 3]
    forward = m[:3, :3] @ np.array([0.0, 0.0, 1.0])
    up = m[:3, :3] @ np.array([0.0, 1.0, 0.0])
    w, h = (int(v) for v in sensor.film().crop_size())
    params = mi.traverse(sensor)
    x_fov = float(params["x_fov"][0] if hasattr(params["x_fov"], "__len__") else params["x_fov"])
    fov_y = math.degrees(2.0 * math.atan(math.tan(math.radians(x_fov) / 2.0) * h / w))
    return list(pos), list(pos + forward), list(up / np.linalg.norm(up)), fov_y, w, h


def _mis(a: float, b: float) -> float:
    """The power heuristic, as Mitsuba's ``mis_weight``."""
    a2 = a * a
    w = a2 / (a2 + b * b) if a2 + b * b > 0 else 0.0
    return w if math.isfinite(w) else 0.0


def record(
    scene: Any,
    out: PathLike,
    spp: int = 4,
    max_depth: int = 5,
    rr_depth: int = 5,
    size: Optional[Tuple[int, int]] = None,
    seed: int = 0,
    bug: Optional[str] = None,
    progress: bool = False,
    sites: bool = False,
) -> Dict[str, Any]:
    """Renders ``scene`` with Mitsuba's path tracer and records every ray into the dataset
    directory ``out`` (see the module's text). ``max_depth`` and ``rr_depth`` mean what they
    mean for Mitsuba's ``path`` integrator (``max_depth=-1``: no limit but Russian roulette).
    ``bug="shadow-dir"`` aims the shadow rays of floor-like surfaces (normal up) at the light's
    mirror image below the floor, on purpose, for the paper's wrong-shadow query to find.
    ``sites=True`` records each ray's site: the line of this integrator that traced it.

    Returns the image (``"image"``, (height, width, 3) float32, the mean radiance per pixel,
    also written beside the trace as its picture), ray counts by kind and by (kind, depth) as
    traced, and the seconds spent."""
    mi = _mitsuba()
    if bug not in (None, "shadow-dir"):
        raise RecordError(f"bug {bug!r}: the one injectable bug is 'shadow-dir'")
    if spp < 1:
        raise RecordError(f"spp {spp}: at least one sample per pixel")
    sc = load(scene, size)
    sensor = sc.sensors()[0]
    tris, mats, colors, emission, names, offsets, skipped = _geometry(mi, sc)
    shapes = sc.shapes()
    shape_index = {sh: i for i, sh in enumerate(shapes)}
    meshes = [sh.is_mesh() for sh in shapes]
    pos, target, up, fov_y, w, h = _camera(mi, sensor)
    depth_limit = max_depth if max_depth >= 0 else 1 << 30
    ctx = mi.BSDFContext()
    sampler = sensor.sampler().clone()
    flags = mi.BSDFFlags

    # Per ray: tree (path index), parent index in the tree, origin, direction, t, kind, prim,
    # throughput, radiance; per path: pixel and sample.
    rays: Dict[str, List[Any]] = {k: [] for k in ("tree", "parent", "o", "d", "t", "kind", "prim", "tp", "rad", "depth", "site")}
    pixels: List[Tuple[int, int]] = []
    samples: List[int] = []
    image = np.zeros((h, w, 3), np.float64)
    counts = {k: 0 for k in KINDS}
    by_depth: Dict[Tuple[str, int], int] = {}

    def prim_of(si: Any) -> int:
        i = shape_index.get(si.shape)
        return -1 if i is None or not meshes[i] else offsets[i] + int(si.prim_index)

    def add(tree: int, parent: int, o: Any, d: Any, t: Optional[float], kind: str, prim: int, tp: Any, rad: Any) -> int:
        if sites:
            f = sys._getframe(1)
            rays["site"].append((f.f_code.co_filename, f.f_lineno, f.f_code.co_name))
        rays["tree"].append(tree)
        rays["parent"].append(parent)
        rays["o"].append((float(o[0]), float(o[1]), float(o[2])))
        n = math.sqrt(float(d[0]) ** 2 + float(d[1]) ** 2 + float(d[2]) ** 2) or 1.0
        rays["d"].append((float(d[0]) / n, float(d[1]) / n, float(d[2]) / n))
        rays["t"].append(float("nan") if t is None else float(t) * n)
        rays["kind"].append(kind)
        rays["prim"].append(prim)
        rays["tp"].append(_rgb(tp))
        rays["rad"].append(_rgb(rad))
        depth = 0 if parent < 0 else rays["depth"][first[0] + parent] + 1
        rays["depth"].append(depth)
        counts[kind] += 1
        by_depth[(kind, depth)] = by_depth.get((kind, depth), 0) + 1
        return len(rays["tree"]) - 1 - first[0]

    first = [0]
    bar = None
    if progress:
        from . import _Progress

        bar = _Progress("mitsuba path tracer", "paths")
    start = time.perf_counter()
    path = 0
    try:
        for y in range(h):
            for x in range(w):
                for s in range(spp):
                    sampler.seed((seed * 0x9E3779B1 + path) & 0xFFFFFFFF)
                    first[0] = len(rays["tree"])
                    pixels.append((x, y))
                    samples.append(s)
                    wavelength = sampler.next_1d()
                    film_pos = mi.Point2f((x + sampler.next_1d()) / w, (y + sampler.next_1d()) / h)
                    ray, ray_weight = sensor.sample_ray(0.0, wavelength, film_pos, sampler.next_2d())
                    throughput = mi.Color3f(ray_weight)
                    result = mi.Color3f(0.0)
                    eta = 1.0
                    prev_si: Any = None
                    prev_bsdf_pdf, prev_bsdf_delta = 1.0, True
                    parent, kind, depth = -1, "camera", 0
                    while True:
                        si = sc.ray_intersect(ray)
                        hit = bool(si.is_valid())
                        emitted = mi.Color3f(0.0)
                        emitter = si.emitter(sc) if hit else None
                        if emitter is None and not hit and sc.environment() is not None:
                            emitter = sc.environment()
                        if emitter is not None:
                            ds = mi.DirectionSample3f(sc, si, prev_si) if prev_si is not None else None
                            em_pdf = 0.0
                            if not prev_bsdf_delta and ds is not None:
                                em_pdf = float(sc.pdf_emitter_direction(prev_si, ds))
                            emitted = throughput * emitter.eval(si) * _mis(prev_bsdf_pdf, em_pdf)
                            result += emitted
                        me = add(path, parent, ray.o, ray.d, float(si.t) if hit else None, kind, prim_of(si) if hit else -1, throughput, emitted)
                        if not (hit and depth + 1 < depth_limit):
                            break
                        bsdf = si.bsdf(ray)
                        # Next-event estimation: the emitter sample's shadow ray, traced here so
                        # it is recorded (Mitsuba's own visibility test is the same ray).
                        em_contrib = mi.Color3f(0.0)
                        sample_em = mi.has_flag(bsdf.flags(), flags.Smooth)
                        ds, em_weight = sc.sample_emitter_direction(si, sampler.next_2d(), False)
                        wo = si.to_local(ds.d)
                        bsdf_val, bsdf_pdf, bs, bsdf_weight = bsdf.eval_pdf_sample(ctx, si, wo, sampler.next_1d(), sampler.next_2d())
                        if sample_em and float(ds.pdf) != 0.0:
                            shadow = si.spawn_ray_to(ds.p)
                            direction = shadow.d
                            if bug == "shadow-dir" and float(si.n[1]) > 0.9:
                                # The light's mirror image below the surface: a wrong direction.
                                o = np.asarray(shadow.o, np.float64)
                                mirrored = np.asarray(ds.p, np.float64) * [1.0, -1.0, 1.0] + [0.0, 2.0 * float(si.p[1]), 0.0]
                                v = mirrored - o
                                direction = mi.Vector3f(*(v / np.linalg.norm(v)))
                            dist = float(shadow.maxt)
                            blocker = sc.ray_intersect(mi.Ray3f(shadow.o, direction))
                            occluded = bool(blocker.is_valid()) and float(blocker.t) < dist
                            if occluded:
                                t_shadow, prim_shadow = float(blocker.t), prim_of(blocker)
                            else:
                                mis = 1.0 if ds.delta else _mis(float(ds.pdf), float(bsdf_pdf))
                                em_contrib = throughput * em_weight * bsdf_val * mis
                                result += em_contrib
                                # It ends on the emitter (an area light's surface), or at the
                                # sampled point (a point light; nothing there to hit).
                                reached = bool(blocker.is_valid()) and float(blocker.t) <= dist * 1.001 + 1e-4
                                t_shadow = float(blocker.t) if reached else dist
                                prim_shadow = prim_of(blocker) if reached else -1
                            add(path, me, shadow.o, direction, t_shadow, "shadow", prim_shadow, throughput, em_contrib)
                        st = bs.sampled_type
                        if float(bs.pdf) <= 0.0 or not any(float(c) > 0 for c in bsdf_weight):
                            break
                        if mi.has_flag(st, flags.Transmission):
                            kind = "transmission"
                        elif mi.has_flag(st, flags.Delta):
                            kind = "specular"
                        elif mi.has_flag(st, flags.Glossy):
                            kind = "glossy"
                        else:
                            kind = "diffuse"
                        ray = si.spawn_ray(si.to_world(bs.wo))
                        throughput = throughput * bsdf_weight
                        eta *= float(bs.eta)
                        prev_si, prev_bsdf_pdf = si, float(bs.pdf)
                        prev_bsdf_delta = mi.has_flag(st, flags.Delta)
                        parent, depth = me, depth + 1
                        t_max = max(float(c) for c in throughput)
                        if depth >= rr_depth:
                            q = min(t_max * eta * eta, 0.95)
                            if sampler.next_1d() >= q:
                                break
                            throughput = throughput / q
                        if t_max == 0.0:
                            break
                    image[y, x] += np.asarray(_rgb(result))
                    path += 1
            if bar is not None:
                bar(f"mitsuba path tracer, row {y + 1} of {h}", path, w * h * spp)
    finally:
        if bar is not None:
            bar.close()
    traced = time.perf_counter() - start
    image /= spp

    start = time.perf_counter()
    kinds = sorted(set(rays["kind"]))
    code = {k: i for i, k in enumerate(kinds)}
    rec = Recorder(out, payload={"throughput": "f32x3", "radiance": "f32x3"}, sites=sites)
    try:
        rec.set_scene(tris, mats, colors, emission, names, point_lights=_point_lights(mi, sc))
        rec.set_camera(pos, target, up, fov_y, w, h)
        rec.set_image(image)
        rec.set_attributes({"renderer": f"mitsuba {mi.__version__} ({mi.variant()}), path integrator in rtvtk.mitsuba", "spp": str(spp), "max_depth": str(max_depth), "inject_bug": bug or "none"})
        tree = np.asarray(rays["tree"], np.int64)
        rec.add_rays(
            tree=tree,
            parent=np.asarray(rays["parent"], np.int32),
            origin=np.asarray(rays["o"], np.float32),
            direction=np.asarray(rays["d"], np.float32),
            t=np.asarray(rays["t"], np.float32),
            kind=(np.asarray([code[k] for k in rays["kind"]], np.uint8), kinds),
            pixel=np.asarray(pixels, np.uint32)[tree],
            sample=np.asarray(samples, np.uint32)[tree],
            prim=np.asarray(rays["prim"], np.int64),
            throughput=np.asarray(rays["tp"], np.float32),
            radiance=np.asarray(rays["rad"], np.float32),
            _sites=rays["site"] if sites else None,
        )
        summary = rec.finish()
    except BaseException:
        if not rec._closed:
            rec.finish()
        raise
    return {
        **summary,
        **{k: v for k, v in counts.items()},
        "by_kind_and_depth": by_depth,
        "image": image.astype(np.float32),
        "trace_seconds": traced,
        "record_seconds": time.perf_counter() - start,
        "shapes_not_drawn": skipped,
    }

