"""Mitsuba 3 recorded through `rtvtk.mitsuba`: its path tracer's image agrees with `mi.render`'s
built-in `path` integrator within Monte-Carlo noise, the recorded rays are the rays it traced
(counts by kind and depth, radiance summing to the image), the camera ray of a pixel lands on
that pixel, `rtvtk check` accepts the trace, the paper's query finds an injected wrong-direction
shadow ray bug and nothing in a correct trace, and a second XML scene (meshes, two area lights,
glossy, specular and transmitted rays) records as well.

Mitsuba is an optional dependency (`pip install ./python[mitsuba]`); scripts/python-check.sh
installs it, and under CI a missing Mitsuba fails these tests instead of skipping them."""

import math
import os
import subprocess

import numpy as np
import pytest

import rtvtk

try:
    import mitsuba as mi
except ImportError:  # pragma: no cover
    if os.environ.get("CI"):
        pytest.fail("Mitsuba 3 is not installed (pip install mitsuba); CI tests it", pytrace=False)
    pytest.skip("Mitsuba 3 is not installed (pip install ./python[mitsuba])", allow_module_level=True)

import rtvtk.mitsuba as rm  # noqa: E402

from test_rtvtk import rtvtk_cli  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
XML = os.path.join(HERE, "..", "examples", "mitsuba", "two_lights.xml")
WRONG = "kind = 'shadow' AND NOT aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)"


def rel_mse(img, ref):
    """Relative MSE as Mitsuba's tests measure it (offset 1e-2 in the denominator)."""
    return float(((img - ref) ** 2 / (ref**2 + 1e-2)).mean())


def reference(scene, size, max_depth, spp):
    mi.set_variant("scalar_rgb")
    sc = rm.load(scene, size)
    return np.asarray(mi.render(sc, spp=spp, integrator=mi.load_dict({"type": "path", "max_depth": max_depth})))


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    out = tmp_path_factory.mktemp("mi") / "cornell"
    r = rm.record("cornell", str(out), spp=32, max_depth=5, size=(16, 16), seed=1)
    return str(out), r


def test_the_image_agrees_with_mitsubas_path_integrator(cornell, tmp_path):
    _, r32 = cornell
    ref = reference("cornell", (16, 16), 5, 2048)
    r8 = rm.record("cornell", str(tmp_path / "c8"), spp=8, max_depth=5, size=(16, 16), seed=2)
    e8, e32 = rel_mse(r8["image"], ref), rel_mse(r32["image"], ref)
    # Noise falls with the samples (about 1/spp), and at 32 spp the error is what Mitsuba's own
    # integrator makes (measured on 16x16: ours 0.044 at 8 spp and 0.0080 at 32, Mitsuba's
    # 0.033 and 0.0084); the bound leaves more than 3x.
    assert e32 < e8, (e8, e32)
    assert e32 < 0.03, e32
    assert abs(float(r32["image"].mean()) - float(ref.mean())) < 0.05 * float(ref.mean())


def test_the_trace_is_what_the_integrator_traced(cornell):
    out, r = cornell
    s = rtvtk.open(out)
    assert s.check() == []
    cli = subprocess.run([rtvtk_cli(), "check", out], capture_output=True, text=True)
    assert cli.returncode == 0, cli.stdout + cli.stderr
    rows = s.sql("SELECT CAST(kind AS VARCHAR) AS kind, depth, count(*) AS n FROM rays GROUP BY 1, 2").to_pylist()
    assert {(x["kind"], x["depth"]): x["n"] for x in rows} == r["by_kind_and_depth"]
    assert s.info()["trees"] == 16 * 16 * 32
    # The radiance payload sums to the image, pixel by pixel.
    t = s.sql("SELECT pixel_x, pixel_y, sum(radiance[1]) / 32 AS red FROM rays GROUP BY 1, 2").to_pylist()
    assert len(t) == 256
    worst = max(abs(x["red"] - float(r["image"][x["pixel_y"], x["pixel_x"], 0])) for x in t)
    assert worst < 1e-4, worst
    # Mitsuba's emitters are the lights table; a correct trace aims every shadow ray at one.
    assert s.sql("SELECT count(*) AS n FROM lights").column("n")[0].as_py() >= 2
    assert s.sql(f"SELECT count(*) AS n FROM rays WHERE {WRONG}").column("n")[0].as_py() == 0


def test_the_camera_ray_of_a_pixel_lands_on_that_pixel(cornell):
    out, _ = cornell
    s = rtvtk.open(out)
    a = {k: v for k, v in zip(*[s.sql("SELECT key, value FROM attributes").column(c).to_pylist() for c in ("key", "value")])}
    vec = lambda k: np.array([float(x) for x in a[k].split(",")])  # noqa: E731
    pos, target, up = vec("camera.position"), vec("camera.target"), vec("camera.up")
    fov, w, h = math.radians(float(a["camera.fov_y"])), int(a["width"]), int(a["height"])
    f = (target - pos) / np.linalg.norm(target - pos)
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    u = np.cross(right, f)
    cams = s.sql("SELECT pixel_x, pixel_y, origin_x, origin_y, origin_z, dir_x, dir_y, dir_z FROM rays WHERE kind = 'camera'").to_pylist()
    assert len(cams) == 16 * 16 * 32
    k = math.tan(fov / 2)
    for c in cams:
        d = np.array([c["dir_x"], c["dir_y"], c["dir_z"]])
        # The film position rtvtk's camera (rl.h's convention, the viewer's) gives this ray.
        sx, sy = d @ right / (d @ f), d @ u / (d @ f)
        px, py = (sx / (k * w / h) + 1) * w / 2, (1 - sy / k) * h / 2
        assert (int(math.floor(px)), int(math.floor(py))) == (c["pixel_x"], c["pixel_y"]), (px, py, c)
        assert np.allclose([c["origin_x"], c["origin_y"], c["origin_z"]], pos, atol=1e-3)


def test_the_papers_query_finds_an_injected_wrong_shadow_direction(tmp_path):
    r = rm.record("cornell", str(tmp_path / "bug"), spp=2, max_depth=3, size=(16, 16), bug="shadow-dir")
    s = rtvtk.open(tmp_path / "bug")
    wrong = s.sql(
        "SELECT count(*) AS n, max(p.dir_y) AS highest FROM rays s JOIN rays p ON s.tree_id = p.tree_id AND s.parent = p.ray "
        "WHERE s.kind = 'shadow' AND NOT aims_at_light(s.origin_x, s.origin_y, s.origin_z, s.dir_x, s.dir_y, s.dir_z)"
    ).to_pylist()[0]
    assert wrong["n"] > 0 and r["shadow"] > wrong["n"]
    # They leave upward-facing surfaces (the floor, the boxes' tops): every one's parent came down.
    assert wrong["highest"] < 0
    assert s.analyze("bugs").markdown.count("point at no emitter") == 1
    # Recorded with sites, the wrong rays group on the line of the integrator that adds them.
    rm.record("cornell", str(tmp_path / "sites"), spp=1, max_depth=3, size=(8, 8), bug="shadow-dir", sites=True)
    source = open(rm.__file__).read().splitlines()
    line = next(i + 1 for i, text in enumerate(source) if 'add(path, me, shadow.o, direction' in text)
    rows = rtvtk.open(tmp_path / "sites").sql(f"SELECT CAST(site AS VARCHAR) AS site, count(*) AS n FROM rays WHERE {WRONG} GROUP BY 1").to_pylist()
    assert [r["site"] for r in rows] == [f"{rm.__file__}:{line} record"], rows


def test_a_second_xml_scene_with_glossy_glass_area_and_point_lights(tmp_path):
    r = rm.record(XML, str(tmp_path / "xml"), spp=16, max_depth=6, size=(24, 18), seed=4)
    for k in ("camera", "shadow", "diffuse", "glossy", "specular", "transmission"):
        assert r[k] > 0, (k, r)
    s = rtvtk.open(tmp_path / "xml")
    assert s.check() == []
    # Two rectangles (two triangles each) and the point emitter.
    assert s.sql("SELECT count(*) AS n FROM lights").column("n")[0].as_py() == 5
    assert s.sql("SELECT count(*) AS n FROM lights WHERE area = 0").column("n")[0].as_py() == 1
    assert s.sql(f"SELECT count(*) AS n FROM rays WHERE {WRONG}").column("n")[0].as_py() == 0
    ref = reference(XML, (24, 18), 6, 1024)
    # Glass and rough gold are noisier than the box: measured at 16 spp on 24x18, ours 0.12 and
    # Mitsuba's own 0.083.
    assert rel_mse(r["image"], ref) < 0.3, rel_mse(r["image"], ref)
    pic = s.render(layers=["image", "composition", "rays"], pixel=(12, 10), size=(96, 72))
    assert pic.size == (96, 72)


def test_bad_input_is_refused(tmp_path):
    with pytest.raises(rtvtk.RecordError, match="no such Mitsuba scene"):
        rm.record(str(tmp_path / "none.xml"), str(tmp_path / "o"))
    with pytest.raises(rtvtk.RecordError, match="shadow-dir"):
        rm.record("cornell", str(tmp_path / "o2"), bug="everything")
    with pytest.raises(rtvtk.RecordError, match="spp"):
        rm.record("cornell", str(tmp_path / "o3"), spp=0)
