# %% [markdown]
# # rtvtk from Python: record → query → picture
#
# A notebook-style walk through the package (each `# %%` is a cell in Jupyter, VS Code or
# `jupytext`; run it as a script too: `python examples/walkthrough.py OUT_DIR`). A numpy path
# tracer records every ray it traces; SQL asks the trace about its rays; the layered pipeline
# draws the answers over the scene; an analysis writes its report; an immediate-mode recording
# answers SQL while it grows.

# %%
import os
import sys

import rtvtk

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import numpy_tracer  # noqa: E402  (the example tracer beside this file)

out = sys.argv[1] if len(sys.argv) > 1 else "walkthrough-trace"
os.makedirs(out, exist_ok=True)
trace = os.path.join(out, "trace")

# %% [markdown]
# ## 1. Record
# The tracer hands whole wavefronts to `Recorder.add_rays` (numpy arrays), with the scene's
# triangles and the camera, so the viewer and the pictures know the scene.

# %%
stats = numpy_tracer.trace(trace, 48, 48, 4, seed=7)
print({k: stats[k] for k in ("rays", "trees", "camera", "shadow", "diffuse")})
session = rtvtk.open(trace)
assert session.check() == [], "rtvtk check accepts the trace"

# %% [markdown]
# ## 2. Query
# Answers are `pyarrow` tables (no copy); `.to_pandas()` or `polars.from_arrow` take them.

# %%
by_kind = session.sql(
    "SELECT kind, depth, count(*) AS rays, avg(t) AS mean_t FROM rays GROUP BY kind, depth ORDER BY kind, depth",
    progress=True,
)
print(by_kind.to_pandas())
# The paper's bug hunt: shadow rays that aim at no light.
wrong = session.sql(
    "SELECT count(*) AS n FROM rays WHERE kind = 'shadow' "
    "AND NOT aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)"
).column("n")[0].as_py()
print(f"shadow rays aiming at no light: {wrong}")
# A finding: shadow rays that end almost where they start, on the surface they leave (the light
# is behind that surface). Correctly occluded, but traced for nothing: a tracer checks the
# cosine towards the light first.
wasted = session.sql(
    "SELECT count(*) AS n FROM rays s JOIN rays p ON s.tree_id = p.tree_id AND s.parent = p.ray "
    "WHERE s.kind = 'shadow' AND s.prim = p.prim AND s.t < 1e-3"
).column("n")[0].as_py()
print(f"shadow rays stopped by their own surface: {wasted} of {stats['shadow']}")
# The ray trees of one pixel.
print(session.trees_at_pixel(24, 30, sample=0).select(["tree_id", "ray", "parent", "kind", "t"]).to_pandas())

# %% [markdown]
# ## 3. Pictures
# `render` draws what `rtvtk render` draws: here the first shadow rays of the pixels on the floor
# in front of the block (a query layer, coloured by hit distance) over the path-traced picture.
# Those that reach the light (long, yellow) converge on it, as in the paper's Figure 5; those the
# block stops are short (purple). In Jupyter the picture shows inline.

# %%
shadows = session.render(
    layers=["image", "composition", "query"],
    sql="SELECT * FROM rays WHERE kind = 'shadow' AND depth = 1 AND pixel_x BETWEEN 26 AND 38 AND pixel_y BETWEEN 34 AND 46",
    colour_by="t",
    size=(480, 480),
    progress=True,
)
shadows.save(os.path.join(out, "shadow_rays.png"))
pixel = session.render(layers=["geometry", "composition", "rays"], pixel=(24, 30), size=(480, 480))
pixel.save(os.path.join(out, "pixel_rays.png"))
print("pictures:", os.path.join(out, "shadow_rays.png"), os.path.join(out, "pixel_rays.png"))

# %% [markdown]
# ## 4. Analyses
# `rtvtk analyze`'s analyses, with the report it writes (markdown and heatmaps).

# %%
report = session.analyze("coherence", width=8, progress=True)
print(report.save(os.path.join(out, "coherence")))
print(report.markdown.split("## Packets")[0])

# %% [markdown]
# ## 5. Immediate mode: query while recording
# The trace stays in memory; each query sees every ray recorded before it.

# %%
live = rtvtk.Recorder.immediate(payload={"throughput": "f32x3"})
numpy_tracer.trace(live, 16, 16, 1, seed=1)
live_sql = live.session()
print(live_sql.sql("SELECT count(*) AS rays FROM rays").to_pylist())
numpy_tracer.trace(live, 16, 16, 1, seed=2)
print(live_sql.sql("SELECT count(*) AS rays FROM rays").to_pylist())

# %% [markdown]
# ## 6. The viewer
# `session.view()` opens the interactive viewer on this session's engine (it needs a display).

# %%
if os.environ.get("RTVTK_WALKTHROUGH_VIEW"):
    session.view()
