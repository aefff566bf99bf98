"""The Python package end to end: a numpy path tracer records through it, `rtvtk check` accepts
the dataset, SQL answers agree with DuckDB on the exported plain Parquet, pictures and analysis
reports equal the CLI's, an immediate-mode recording answers SQL while it grows, the viewer
opens on the session's engine, Ctrl-C stops a query, and bad input raises `rtvtk.Error`
subclasses (a Rust panic too)."""

import os
import shutil
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
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
    cam = t.filter(pc.equal(t.column("kind"), "camera"))
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
    with pytest.raises(rtvtk.DatasetError, match="manifest"):
        rtvtk.open(tmp_path / "nowhere")
    s = rtvtk.open(out)
    with pytest.raises(rtvtk.QueryError, match="nope"):
        s.sql("SELECT nope FROM rays")
    with pytest.raises(rtvtk.QueryError, match="DDL|not supported|statement"):
        s.sql("CREATE TABLE x AS SELECT 1")
    # An error while the query runs (not while it is planned) is a QueryError too, not pyarrow's.
    with pytest.raises(rtvtk.QueryError, match="Cast error|cast|parse"):
        s.sql("SELECT CAST(CAST(kind AS VARCHAR) AS INT) FROM rays")
    with pytest.raises(rtvtk.RenderError, match="unknown option"):
        s.render(colour="red")
    with pytest.raises(rtvtk.RenderError, match="unknown layer"):
        s.render(layers=["raytrees"])
    with pytest.raises(rtvtk.QueryError, match="unknown analysis"):
        s.analyze("speed")
    with pytest.raises(rtvtk.QueryError, match="unknown option"):
        s.analyze("bvh", depth=3)
    with pytest.raises(rtvtk.QueryError, match="two datasets"):
        s.analyze("diff")
    with pytest.raises(rtvtk.RecordError, match="f16"):
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
    with pytest.raises(rtvtk.QueryError, match="connect"):
        rtvtk.connect("grpc://127.0.0.1:1")
    with pytest.raises(rtvtk.RecordError, match="immediate"):
        rec.session()
    # Every class is an rtvtk.Error.
    for e in (rtvtk.DatasetError, rtvtk.QueryError, rtvtk.RecordError, rtvtk.RenderError, rtvtk.InternalError):
        assert issubclass(e, rtvtk.Error)


def test_a_rust_panic_is_an_internal_error_and_the_interpreter_goes_on():
    for place in ("call", "thread"):
        with pytest.raises(rtvtk.InternalError, match="panicked"):
            rtvtk._rtvtk._panic_for_tests(place)
    assert rtvtk.Recorder.immediate().rays_recorded() == 0


def test_sql_over_an_immediate_recording_sees_the_rays_recorded_before_each_query():
    rec = rtvtk.Recorder.immediate(payload={"throughput": "f32x3"})
    first = numpy_tracer.trace(rec, 8, 6, 1, seed=3)
    s = rec.session()
    assert "in memory" in repr(s)
    n = s.sql("SELECT count(*) AS n FROM rays").column("n").to_pylist()
    assert n == [first["rays"]]
    assert s.sql("SELECT count(*) AS n FROM trees").column("n").to_pylist() == [first["trees"]]
    # The scene and camera written before the session: tables, attributes and ray functions.
    assert s.sql("SELECT count(*) AS n FROM triangles").column("n").to_pylist()[0] > 0
    assert "camera.position" in s.sql("SELECT key FROM attributes").column("key").to_pylist()
    wrong = s.sql(
        "SELECT count(*) AS n FROM rays WHERE kind = 'shadow' AND NOT aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)"
    )
    assert wrong.column("n").to_pylist() == [0]
    # More rays: the same session's next query sees them.
    second = numpy_tracer.trace(rec, 8, 6, 1, seed=4)
    n = s.sql("SELECT count(*) AS n, count(DISTINCT tree_id) AS trees FROM rays").to_pylist()[0]
    assert n["n"] == first["rays"] + second["rays"] == rec.rays_recorded()
    assert n["trees"] == first["trees"] + second["trees"]
    # And it draws, through the same engine.
    pic = s.render(layers=["geometry", "composition", "rays"], pixel=(4, 3), size=(64, 48))
    assert pic.size == (64, 48)


def test_analyses_write_the_reports_rtvtk_analyze_writes(traced, tmp_path):
    out, _ = traced
    s = rtvtk.open(out)
    for analysis, flags, options in [("bugs", [], {}), ("coherence", ["--width", "4"], {"width": 4})]:
        before = s.queries_run()
        report = s.analyze(analysis, **options)
        assert s.queries_run() > before
        ours = tmp_path / f"py-{analysis}"
        md = report.save(ours)
        assert md == str(ours / "report.md") and report._repr_markdown_() == report.markdown
        cli = tmp_path / f"cli-{analysis}"
        r = subprocess.run([rtvtk_cli(), "analyze", analysis, out, *flags, "--out", str(cli)], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr
        assert (ours / "report.md").read_text() == (cli / "report.md").read_text()
        assert sorted(os.listdir(ours)) == sorted(os.listdir(cli))
        for name, (title, values, cell) in report.grids.items():
            assert (ours / f"{name}.png").read_bytes() == (cli / f"{name}.png").read_bytes(), name
            assert values.ndim == 2 and cell >= 1 and title
    # Two datasets: diff by name.
    two = rtvtk.open({"a": out, "b": out})
    same = two.analyze("diff", tile=8)
    assert "a" in same.markdown and same.grids


def test_progress_true_shows_a_bar(traced, capfd):
    out, stats = traced
    s = rtvtk.open(out)
    t = s.sql("SELECT tree_id FROM rays", progress=True)
    assert t.num_rows == stats["rays"]
    s.analyze("bugs", progress=True)
    s.render(layers=["rays"], size=(32, 24), progress=True)
    err = capfd.readouterr().err
    assert "sql" in err and "rows" in err, err
    assert "analyze bugs" in err and "queries" in err, err


def _run_python(code, timeout, env=None):
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=timeout, env=env)


def test_ctrl_c_stops_a_running_query(traced):
    out, _ = traced
    # A three-way cross join of the trace's rays: billions of rows, minutes of work. SIGINT a
    # second in: the query stops and KeyboardInterrupt reaches the script, which goes on.
    code = f"""
        import os, signal, threading, time
        import rtvtk
        # Python's own Ctrl-C handler, even when the suite runs as a background job (`cmd &` in a
        # shell without job control starts it with SIGINT ignored, and Python then installs none).
        signal.signal(signal.SIGINT, signal.default_int_handler)
        s = rtvtk.open({out!r})
        threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
        start = time.monotonic()
        try:
            s.sql("SELECT sum(a.t + b.t + c.t) AS x FROM rays a, rays b, rays c")
            print("finished")
        except KeyboardInterrupt:
            print("interrupted after", round(time.monotonic() - start, 1))
        print(s.sql("SELECT count(*) AS n FROM rays").column("n").to_pylist())
    """
    r = _run_python(code, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "interrupted after" in r.stdout, r.stdout + r.stderr
    assert "[" in r.stdout.splitlines()[-1], r.stdout


def test_view_without_a_display_says_so_at_once(traced):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    r = _run_python(f"import rtvtk; rtvtk.open({traced[0]!r}).view()", timeout=60, env=env)
    assert r.returncode != 0 and "RenderError" in r.stderr and "DISPLAY" in r.stderr, r.stderr


def test_view_opens_the_viewer_on_the_sessions_engine(traced, tmp_path):
    xvfb = shutil.which("Xvfb")
    if not xvfb:
        pytest.fail("this test needs Xvfb, the virtual X server (scripts/check.sh installs it)")
    # Xvfb picks a free display and writes its number once it accepts connections.
    x = subprocess.Popen([xvfb, "-displayfd", "1", "-screen", "0", "1400x900x24", "-nolisten", "tcp"], stdout=subprocess.PIPE, text=True)
    try:
        number = x.stdout.readline().strip()
        assert number.isdigit(), f"Xvfb did not start (it said {number!r})"
        env = dict(os.environ, DISPLAY=f":{number}", HOME=str(tmp_path), XDG_DATA_HOME=str(tmp_path))
        env.pop("WAYLAND_DISPLAY", None)
        shot = tmp_path / "window.png"
        r = _run_python(f"import rtvtk; rtvtk.open({traced[0]!r}).view(screenshot={str(shot)!r})", timeout=300, env=env)
        assert r.returncode == 0, r.stderr
    finally:
        x.kill()
        x.wait()
    from PIL import Image

    img = Image.open(shot).convert("RGBA")
    assert img.size == (1400, 860), "the window's size"
    # The render pane shows the picture: many distinct colours on the window's left half.
    colours = {img.getpixel((x, y)) for y in range(100, 760, 7) for x in range(20, 700, 7)}
    assert len(colours) > 200, f"the render pane looks empty ({len(colours)} colours)"


def test_the_walkthrough_runs_from_recording_to_pictures(tmp_path):
    script = os.path.join(HERE, "..", "examples", "walkthrough.py")
    r = subprocess.run([sys.executable, script, str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "shadow rays aiming at no light: 0" in r.stdout, r.stdout
    for name in ("shadow_rays.png", "pixel_rays.png", "coherence/report.md"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert rtvtk.open(tmp_path / "trace").check() == []


def test_sites_name_the_python_line_that_added_each_ray(tmp_path):
    rec = rtvtk.Recorder(tmp_path / "s", sites=True)
    with rec.tree(0, 0) as t:
        camera_line = sys._getframe().f_lineno + 1
        t.add_ray((0, 0, 0), (0, 0, 1), 1.0, "camera")
        t.descend()
        shadow_line = sys._getframe().f_lineno + 1
        t.add_ray((0, 0, 1), (0, 1, 0), None, "shadow")
    batch_line = sys._getframe().f_lineno + 1
    rec.add_rays(tree=[0], parent=[-1], origin=[[0, 0, 0]], direction=[[1, 0, 0]], t=[1.0], kind=["camera"], pixel=[[1, 1]])
    rec.add_rays(tree=[0], parent=[-1], origin=[[0, 0, 0]], direction=[[1, 0, 0]], t=[1.0], kind=["camera"], pixel=[[2, 1]], site=("render.cu", 42, "trace"))
    rec.finish()
    rows = rtvtk.open(tmp_path / "s").sql("SELECT CAST(site AS VARCHAR) AS site FROM rays ORDER BY tree_id, ray").column("site").to_pylist()
    me = "test_sites_name_the_python_line_that_added_each_ray"
    assert rows == [f"{__file__}:{camera_line} {me}", f"{__file__}:{shadow_line} {me}", f"{__file__}:{batch_line} {me}", "render.cu:42 trace"]
    # Without sites, no site column.
    plain = rtvtk.Recorder(tmp_path / "p")
    with plain.tree(0, 0) as t:
        t.add_ray((0, 0, 0), (0, 0, 1), 1.0, "camera")
    plain.finish()
    with pytest.raises(rtvtk.QueryError, match="site"):
        rtvtk.open(tmp_path / "p").sql("SELECT site FROM rays")


@pytest.mark.parametrize("table", ["lights", "triangles"])
def test_a_broken_table_raises_dataset_error_for_that_table_alone(tmp_path, traced, table):
    """A table whose file was changed behind the manifest's back (a flipped byte): the session
    opens, the rays answer, the picture draws, and only queries of that table (and what is made
    from it) raise `rtvtk.DatasetError`, naming it."""
    out, _ = traced
    copy = tmp_path / "t"
    shutil.copytree(out, copy)
    f = copy / "tables" / f"{table}.parquet"
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x5A
    f.write_bytes(bytes(data))
    s = rtvtk.open(copy)
    n = s.sql("SELECT count(*) AS n FROM rays").column("n").to_pylist()[0]
    assert n == rtvtk.open(out).sql("SELECT count(*) AS n FROM rays").column("n").to_pylist()[0]
    with pytest.raises(rtvtk.DatasetError, match=f"`{table}`"):
        s.sql(f"SELECT * FROM {table}")
    checks = s.sql("SELECT problem, missing FROM numerics_checks").to_pylist()
    needs = {"lights": "wrong_shadow", "triangles": "leak"}[table]
    assert any(c["problem"] == needs and f"`{table}` table is unavailable" in (c["missing"] or "") for c in checks)
    pic = s.render(layers=["rays"], size=(64, 48))
    assert pic.size == (64, 48)
