"""Mitsuba 3's Cornell box, recorded: every ray of Mitsuba's path tracer into an rtvtk dataset,
then one pixel's path trees drawn over Mitsuba's geometry and over Mitsuba's own picture.

    pip install ./python[mitsuba]
    python examples/mitsuba_cornell.py OUT_DIR
    rtvtk view OUT_DIR/cornell
"""

import os
import sys

import rtvtk
import rtvtk.mitsuba

out = sys.argv[1] if len(sys.argv) > 1 else "mitsuba-trace"
os.makedirs(out, exist_ok=True)
trace = os.path.join(out, "cornell")
r = rtvtk.mitsuba.record("cornell", trace, spp=16, max_depth=5, size=(64, 64), progress=True)
print({k: r[k] for k in ("trees", "rays", "camera", "shadow", "diffuse")}, f"traced in {r['trace_seconds']:.1f} s")

s = rtvtk.open(trace)
print(s.sql("SELECT kind, depth, count(*) AS rays FROM rays GROUP BY kind, depth ORDER BY kind, depth").to_pandas())
wrong = s.sql(
    "SELECT count(*) AS n FROM rays WHERE kind = 'shadow' AND NOT aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)"
).column("n")[0].as_py()
print(f"shadow rays aiming at no light: {wrong}")

# One pixel's path trees (16 samples) over Mitsuba's geometry, and over Mitsuba's picture.
pixel = (40, 44)
s.render(layers=["geometry", "composition", "rays"], pixel=pixel, size=(512, 512), geometry="wireframe").save(os.path.join(out, "cornell_pixel_geometry.png"))
s.render(layers=["image", "composition", "rays"], pixel=pixel, size=(512, 512)).save(os.path.join(out, "cornell_pixel.png"))
print("pictures:", os.path.join(out, "cornell_pixel.png"), os.path.join(out, "cornell_pixel_geometry.png"))
