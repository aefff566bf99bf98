"""The Python package end to end: a numpy path tracer records through it, `rtvtk check` accepts
the dataset, SQL answers agree with DuckDB on the exported plain Parquet, pictures equal the
CLI's, and bad input raises `rtvtk.Error`."""

import os
import shutil
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import rtvtk

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "examples"))
import numpy_tracer  # noqa: E402


def rtvtk_cli():
    """The command line built beside the package (scripts/check.sh builds it first)."""
    exe = os.environ.get("RTVTK_BIN") or shutil.which("rtvtk")
    if not exe:
        pytest.fail("set RTVTK_BIN to the rtvtk binary (target/debug/rtvtk)")
    return exe


@pytest.fixture(scope="session")
def traced(tmp_path_factory):
    out = tmp_path_factory.mktemp("trace") / "t"
    stats = numpy_tracer.trace(str(out), 16, 12, 2, seed=1)
    return str(out), stats


def test_a_numpy_tracer_records_a_dataset_rtvtk_check_accepts(traced):
    out, stats = traced
    assert stats["trees"] == 16 * 12 * 2
    assert stats["rays"] == stats["camera"] + stats["shadow"] + stats["diffuse"]
    assert stats["shadow"] > 0 and stats["diffuse"] > 0
    r = subprocess.run([rtvtk_cli(), "check", out], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    s = rtvtk.open(out)
    assert s.check() == []
    info = s.info()
    assert info["rays"] == stats["rays"] and info["trees"] == stats["trees"]
    assert ("throughput", "f32x3") in info["payload"]
    assert "triangles" in info["tables"] and "lights" in info["tables"]


def test_counts_by_kind_match_what_the_tracer_traced(traced):
    out, stats = traced
    t = rtvtk.open(out).sql("SELECT kind, count(*) AS n FROM rays GROUP BY kind")
    got = {k: n for k, n in zip(t.column("kind").to_pylist(), t.column("n").to_pylist())}
    assert got == {"camera": stats["camera"], "shadow": stats["shadow"], "diffuse": stats["diffuse"]}
    # A correct tracer's shadow rays all aim at the light: the paper's query finds none wrong.
    wrong = rtvtk.open(out).sql(
        "SELECT count(*) AS n FROM rays WHERE kind = 'shadow' AND NOT aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)"
    )
    assert wrong.column("n").to_pylist() == [0]


def test_the_camera_ray_of_a_pixel_lands_on_that_pixel(traced):
    out, _ = traced
    s = rtvtk.open(out)
    t = s.trees_at_pixel(5, 7, sample=0)
    cam = t.filter(pa.compute.equal(t.column("kind"), "camera"))
    assert cam.num_rows == 1
    assert s.tree(cam.column("tree_id")[0].as_py()).num_rows >= 1


def test_sql_agrees_with_duckdb_on_the_exported_dataset(traced, tmp_path):
    duckdb = pytest.importorskip("duckdb")
    out, _ = traced
    plain = tmp_path / "plain"
    r = subprocess.run([rtvtk_cli(), "export", out, str(plain)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    q = "SELECT kind, depth, count(*) AS n, round(sum(dir_y), 3) AS dy FROM rays GROUP BY kind, depth ORDER BY kind, depth"
    ours = rtvtk.open(out).sql(q).to_pylist()
    files = [str(p) for p in plain.rglob("*.parquet") if "rays" in p.name]
    assert files, list(plain.rglob("*"))
    con = duckdb.connect()
    con.execute(f"CREATE VIEW rays AS SELECT * FROM read_parquet({files!r})")
    theirs = [dict(zip(["kind", "depth", "n", "dy"], row)) for row in con.execute(q).fetchall()]
    assert [(r["kind"], r["depth"], r["n"]) for r in ours] == [(r["kind"], r["depth"], r["n"]) for r in theirs]
    for a, b in zip(ours, theirs):
        assert a["dy"] == pytest.approx(b["dy"], abs=2e-3)


def test_results_stream_and_go_to_pandas(traced):
    out, stats = traced
    s = rtvtk.open({"a": out})
    reader = s.sql_batches("SELECT tree_id, ray, origin_x FROM a.rays")
    rows = sum(b.num_rows for b in reader)
    assert rows == stats["rays"]
    df = s.sql("SELECT count(*) AS n FROM rays").to_pandas()
    assert int(df["n"][0]) == stats["rays"]
    assert "a.rays" in s.tables() and "rays" in s.tables()


def test_render_returns_the_picture_rtvtk_render_draws(traced, tmp_path):
    out, _ = traced
    pic = rtvtk.open(out).render(layers=["geometry", "composition", "rays"], pixel=(8, 6), size=(96, 72))
    assert pic.size == (96, 72)
    assert pic._repr_png_()[:8] == b"\x89PNG\r\n\x1a\n"
    ours = tmp_path / "py.png"
    pic.save(ours)
    cli = tmp_path / "cli.png"
    r = subprocess.run(
        [rtvtk_cli(), "render", out, "--layers", "geometry,composition,rays", "--pixel", "8,6", "--size", "96x72", "--out", str(cli)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    assert ours.read_bytes() == cli.read_bytes(), "the package and the CLI draw the same picture"


def test_trees_recorded_one_by_one_and_immediate_mode(tmp_path):
    rec = rtvtk.Recorder(tmp_path / "one", payload={"weight": "f32"})
    with rec.tree(1, 2, 0) as t:
        t.add_ray((0, 0, 0), (0, 0, 1), 2.0, "camera", prim=3, weight=1.0)
        t.descend()
        t.add_ray((0, 0, 2), (0, 1, 0), None, "shadow", weight=0.5)
        t.add_ray((0, 0, 2), (1, 0, 0), 1.0, "diffuse", weight=0.25)
    summary = rec.finish()
    assert summary["trees"] == 1 and summary["rays"] == 3
    t = rtvtk.open(tmp_path / "one").sql("SELECT ray, parent, kind, t, weight FROM rays ORDER BY ray").to_pylist()
    assert [(r["ray"], r["parent"], r["kind"]) for r in t] == [(0, None, "camera"), (1, 0, "shadow"), (2, 0, "diffuse")]
    assert t[1]["t"] is None and t[2]["weight"] == 0.25
    mem = rtvtk.Recorder.immediate()
    with mem.tree(0, 0) as t:
        t.add_ray((0, 0, 0), (0, 0, 1), 1.0, "camera")
    assert mem.rays_recorded() == 1
    # A tree ended inside its block is recorded once, and takes no more rays.
    with mem.tree(1, 0) as t:
        t.add_ray((0, 0, 0), (0, 0, 1), 1.0, "camera")
        t.end()
        with pytest.raises(rtvtk.Error, match="already recorded"):
            t.add_ray((0, 0, 0), (0, 0, 1), 1.0, "camera")
    assert mem.rays_recorded() == 2


def test_bad_input_raises_rtvtk_error(tmp_path, traced):
    out, _ = traced
    with pytest.raises(rtvtk.Error, match="manifest"):
        rtvtk.open(tmp_path / "nowhere")
    s = rtvtk.open(out)
    with pytest.raises(rtvtk.Error, match="nope"):
        s.sql("SELECT nope FROM rays")
    with pytest.raises(rtvtk.Error, match="DDL|not supported|statement"):
        s.sql("CREATE TABLE x AS SELECT 1")
    with pytest.raises(rtvtk.Error, match="unknown option"):
        s.render(colour="red")
    with pytest.raises(rtvtk.Error, match="unknown layer"):
        s.render(layers=["raytrees"])
    with pytest.raises(rtvtk.Error, match="f16"):
        rtvtk.Recorder(tmp_path / "p", payload={"w": "f16"})
    rec = rtvtk.Recorder(tmp_path / "q", payload={"w": "f32x3"})
    with pytest.raises(rtvtk.Error, match="float32"):
        rec.add_rays(tree=[0], parent=[-1], origin=[[0, 0, 0]], direction=[[0, 0, 1]], t=[1.0], kind=["camera"], pixel=[[0, 0]], w=np.zeros((1, 3), np.float64))
    with pytest.raises(rtvtk.Error, match="parent 5"):
        rec.add_rays(tree=[0], parent=[5], origin=[[0, 0, 0]], direction=[[0, 0, 1]], t=[1.0], kind=["camera"], pixel=[[0, 0]], w=np.zeros((1, 3), np.float32))
    with pytest.raises(rtvtk.Error, match="90 values, expected 3|values, expected"):
        rec.add_rays(tree=[0], parent=[-1], origin=np.zeros(90, np.float32), direction=[[0, 0, 1]], t=[1.0], kind=["camera"], pixel=[[0, 0]], w=np.zeros((1, 3), np.float32))
    with pytest.raises(rtvtk.Error, match="not declared"):
        with rec.tree(0, 0) as t:
            t.add_ray((0, 0, 0), (0, 0, 1), 1.0, "camera", colour=1.0)
    with pytest.raises(rtvtk.Error, match="camera"):
        rec.set_camera((0, 0, 0), (0, 0, 0), (0, 1, 0), 40, 8, 8)
    rec.finish()
    with pytest.raises(rtvtk.Error, match="finished"):
        rec.add_rays(tree=[0], parent=[-1], origin=[[0, 0, 0]], direction=[[0, 0, 1]], t=[1.0], kind=["camera"], pixel=[[0, 0]])
    with pytest.raises(rtvtk.Error, match="connect"):
        rtvtk.connect("grpc://127.0.0.1:1")
