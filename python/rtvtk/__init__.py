"""rtvtk: record, store, query and draw the rays a ray tracer traces.

The same engine as the ``rtvtk`` command line: ``open`` and ``connect`` give a ``Session`` whose
SQL answers arrive as ``pyarrow`` tables (through the Arrow C stream interface, no copy);
``Recorder`` writes a dataset from a Python renderer (or keeps it in memory, queryable while
recording); ``Session.render`` draws the layered pictures ``rtvtk render`` draws,
``Session.analyze`` runs ``rtvtk analyze``'s analyses and ``Session.view`` opens the viewer.

Errors are ``rtvtk.Error`` subclasses: ``DatasetError`` (opening, reading), ``QueryError`` (SQL,
analyses), ``RecordError`` (recording input), ``RenderError`` (pictures, the window) and
``InternalError`` (a failure inside rtvtk itself). Long calls release the GIL, Ctrl-C cancels
them (``KeyboardInterrupt``), and ``progress=True`` shows a bar (tqdm's when installed).
"""

from __future__ import annotations

import builtins
import contextlib
import os
import sys
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import pyarrow as pa
import pyarrow.compute  # noqa: F401  (pa.compute)

from . import _rtvtk
from ._rtvtk import DatasetError, Error, InternalError, QueryError, RecordError, RenderError

__all__ = [
    "Error",
    "DatasetError",
    "QueryError",
    "RecordError",
    "RenderError",
    "InternalError",
    "Session",
    "Picture",
    "Report",
    "Recorder",
    "Tree",
    "open",
    "connect",
    "KINDS",
]
__version__ = _rtvtk.__version__

#: The built-in ray kinds, in the order of their codes.
KINDS = ("camera", "shadow", "diffuse", "specular", "transmission")

PathLike = Union[str, "os.PathLike[str]"]


def _name_of(path: PathLike) -> str:
    base = os.path.basename(os.path.normpath(os.fspath(path)))
    name = "".join(c if c.isalnum() else "_" for c in base)
    if not name or name[0].isdigit():
        name = "t_" + name
    return name


def open(datasets: Union[PathLike, Sequence[PathLike], Mapping[str, PathLike]]) -> "Session":
    """Opens one dataset (a path), several (a list, or ``{"name": path}``): each dataset's tables
    are ``NAME.rays``, ``NAME.trees``, ...; the first one's also plain ``rays``, ``trees``."""
    if isinstance(datasets, Mapping):
        pairs = [(str(k), os.fspath(v)) for k, v in datasets.items()]
    elif isinstance(datasets, (str, os.PathLike)):
        pairs = [(_name_of(datasets), os.fspath(datasets))]
    else:
        pairs = [(_name_of(p), os.fspath(p)) for p in datasets]
    return Session(_rtvtk.Session.open(pairs))


def connect(url: str, token: Optional[str] = None) -> "Session":
    """Connects to a running ``rtvtk serve`` (``grpc://HOST:PORT``), with its bearer token."""
    return Session(_rtvtk.Session.connect(url, token))


class Picture:
    """A PNG picture: shows inline in Jupyter, saves with ``save``."""

    def __init__(self, png: bytes, report: List[str]):
        self.png = png
        #: What the layers reported (rays drawn, what the dataset lacks, ...).
        self.report = report

    def _repr_png_(self) -> bytes:
        return self.png

    def save(self, path: PathLike) -> None:
        with builtins.open(path, "wb") as f:
            f.write(self.png)

    @property
    def size(self) -> Tuple[int, int]:
        """Width and height in pixels (from the PNG header)."""
        w = int.from_bytes(self.png[16:20], "big")
        h = int.from_bytes(self.png[20:24], "big")
        return (w, h)


class _TextBar:
    """A one-line progress bar on stderr, for when tqdm is not installed."""

    def __init__(self, desc: str, unit: str):
        import time

        self._out = sys.stderr
        self._time = time.monotonic
        self._start = self._time()
        self._last = 0.0
        self.desc, self.unit, self.n, self.total = desc, unit, 0, None

    def refresh(self) -> None:
        now = self._time()
        if now - self._last < 0.1:
            return
        self._last = now
        took = now - self._start
        if self.total:
            frac = min(1.0, self.n / self.total)
            bar = "#" * int(frac * 24)
            line = f"{self.desc}: {frac * 100:3.0f}% [{bar:<24}] {self.n}/{self.total} {self.unit} {took:.1f}s"
        elif self.n:
            line = f"{self.desc}: {self.n} {self.unit} {took:.1f}s"
        else:
            line = f"{self.desc}: {took:.1f}s"
        self._out.write("\r" + line[:120])
        self._out.flush()

    def close(self) -> None:
        self._last = 0.0
        self.refresh()
        self._out.write("\n")
        self._out.flush()


class _Progress:
    """``progress=True``: a bar fed by the native side's ``(what, done, total)`` reports (total
    0: not known) or by rows as they arrive."""

    def __init__(self, desc: str, unit: str):
        try:
            from tqdm.auto import tqdm

            self._bar: Any = tqdm(desc=desc, unit=unit, total=None, unit_scale=True)
        except ImportError:
            self._bar = _TextBar(desc, unit)

    def __call__(self, what: str, done: int, total: int) -> None:
        bar = self._bar
        if what and getattr(bar, "desc", None) != what:
            if hasattr(bar, "set_description_str"):
                bar.set_description_str(what, refresh=False)
            else:
                bar.desc = what
        bar.total = total or None
        bar.n = done
        bar.refresh()

    def add(self, n: int) -> None:
        self._bar.n += n
        self._bar.refresh()

    def close(self) -> None:
        self._bar.close()


@contextlib.contextmanager
def _progress(enabled: bool, desc: str, unit: str) -> Iterator[Optional[_Progress]]:
    if not enabled:
        yield None
        return
    bar = _Progress(desc, unit)
    try:
        yield bar
    finally:
        bar.close()


def _unique_dictionaries(batch: pa.RecordBatch) -> pa.RecordBatch:
    """The batch with every dictionary column's dictionary free of repeats. The engine may
    hand a grouped or sorted `kind` column over with a dictionary that repeats values (valid
    Arrow), which pandas refuses as categories; such a column is encoded again."""
    columns = list(batch.columns)
    changed = False
    for i, c in enumerate(columns):
        if pa.types.is_dictionary(c.type) and len(c.dictionary) > len(pa.compute.unique(c.dictionary)):
            columns[i] = c.dictionary_decode().dictionary_encode().cast(c.type)
            changed = True
    return pa.RecordBatch.from_arrays(columns, schema=batch.schema) if changed else batch


def _batches(native_stream: Any, reader: pa.RecordBatchReader, bar: Optional[_Progress]) -> Iterator[pa.RecordBatch]:
    """A query's batches as they arrive; the stream's own failure (Ctrl-C, the engine's error)
    raised as itself rather than as pyarrow's wrapping of it."""
    try:
        for batch in reader:
            if bar is not None:
                bar.add(batch.num_rows)
            yield _unique_dictionaries(batch)
    except Exception as e:
        failure = native_stream.failure()
        if failure is not None:
            raise failure from None
        raise QueryError(str(e)) from e


class Report:
    """An analysis's report (``Session.analyze``): markdown, and the grids it shows as numpy
    arrays (NaN where there is no data). Shows as markdown in Jupyter; ``save`` writes it as
    ``rtvtk analyze --out`` does."""

    def __init__(self, native: Any):
        self._native = native
        #: The report's text (markdown); its pictures are the grids, by name.
        self.markdown: str = native.markdown
        #: Grid name -> (title, values of shape (height, width), pixels per cell).
        self.grids: Dict[str, Tuple[str, np.ndarray, int]] = {
            name: (title, np.asarray(values, dtype=np.float64).reshape(h, w), cell)
            for name, title, w, h, cell, values in native.grids()
        }

    def save(self, directory: PathLike) -> str:
        """Writes ``report.md`` and a heatmap PNG per grid into ``directory``; returns the path
        of ``report.md``."""
        return str(self._native.save(os.fspath(directory)))

    def _repr_markdown_(self) -> str:
        return self.markdown

    def __str__(self) -> str:
        return self.markdown


class Session:
    """SQL over traces and the pictures drawn from them (see ``open`` and ``connect``)."""

    def __init__(self, native: Any):
        self._native = native

    def sql(self, query: str, progress: bool = False) -> pa.Table:
        """Runs a read-only query; the whole result as a ``pyarrow.Table`` (Arrow's C stream,
        no copy). ``progress=True`` counts the rows as they arrive; Ctrl-C stops the query."""
        native = self._native.stream(query)
        reader = pa.RecordBatchReader.from_stream(native)
        with _progress(progress, "sql", "rows") as bar:
            batches = list(_batches(native, reader, bar))
        return pa.Table.from_batches(batches, schema=reader.schema)

    def sql_batches(self, query: str) -> pa.RecordBatchReader:
        """Runs a read-only query; its batches as they come (results larger than memory)."""
        native = self._native.stream(query)
        reader = pa.RecordBatchReader.from_stream(native)
        return pa.RecordBatchReader.from_batches(reader.schema, _batches(native, reader, None))

    def tables(self) -> List[str]:
        """The tables queries can name."""
        return list(self._native.tables())

    def tree(self, tree_id: int) -> pa.Table:
        """Every ray of one tree, in order."""
        return self.sql(f"SELECT * FROM rays WHERE tree_id = {int(tree_id)} ORDER BY ray")

    def trees_at_pixel(self, x: int, y: int, sample: Optional[int] = None) -> pa.Table:
        """Every ray of the trees of pixel (x, y) (and one sample)."""
        where = f"pixel_x = {int(x)} AND pixel_y = {int(y)}"
        if sample is not None:
            where += f" AND sample = {int(sample)}"
        return self.sql(f"SELECT * FROM rays WHERE {where} ORDER BY tree_id, ray")

    def info(self, name: Optional[str] = None) -> Dict[str, Any]:
        """Counts, segments, tables, payload and attributes of a dataset opened here."""
        return dict(self._native.info(name))

    def check(self, name: Optional[str] = None) -> List[str]:
        """``rtvtk check``: the errors found (an empty list: the dataset is consistent)."""
        return list(self._native.check(name))

    def render(self, progress: bool = False, **options: Any) -> Picture:
        """``rtvtk render`` with the same options: ``layers=["geometry", "rays"]``,
        ``pixel=(x, y)``, ``tree=``, ``sample=``, ``kinds=[...]``, ``depth=(a, b)``,
        ``max_rays=``, ``sql=``, ``colour_by=``, ``bvh_levels=(a, b)``, ``bvh_visited=``,
        ``geometry="wireframe"``, ``camera=((x, y, z), (x, y, z), fov)``, ``size=(w, h)``,
        ``line_width=``, ``image_source=``, ``image_spp=``, ``legend=``. ``progress=True``
        shows the rays loading; Ctrl-C stops the render."""
        with _progress(progress, "render", "rays") as bar:
            png, report = self._native.render(options, bar)
        return Picture(bytes(png), list(report))

    def analyze(self, analysis: str, progress: bool = False, **options: Any) -> Report:
        """One of ``rtvtk analyze``'s analyses on this session's engine: ``"coherence"``
        (``width=8``, ``orders=["trace", "morton", "octant", "material"]``, ``kind=None``),
        ``"bvh"`` (``level=3``), ``"numerics"`` (old name ``"bugs"``), or ``"diff"`` (``a=``, ``b=`` dataset names, by
        default the first two opened; ``tile=16``). ``progress=True`` counts its queries;
        Ctrl-C stops it."""
        with _progress(progress, f"analyze {analysis}", "queries") as bar:
            return Report(self._native.analyze(analysis, options, bar))

    def view(self, dataset: Optional[str] = None, screenshot: Optional[PathLike] = None, tracer: Optional[str] = None) -> None:
        """Opens the interactive viewer on this session's engine (its first dataset, or
        ``dataset``) and returns when its window is closed. With ``screenshot``, the window is
        written there once everything is drawn, and closes. One window per process, from the
        main thread (winit's rule); it needs a display (``DISPLAY`` or ``WAYLAND_DISPLAY``)."""
        if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            raise RenderError("view needs a display: neither DISPLAY nor WAYLAND_DISPLAY is set (use render() for pictures without one)")
        self._native.view(dataset, None if screenshot is None else os.fspath(screenshot), tracer)

    def queries_run(self) -> int:
        """How many queries this session has run (an analysis runs many)."""
        return int(self._native.queries_run())

    def __repr__(self) -> str:
        return f"rtvtk.Session({self._native.describe()})"


class Tree:
    """One ray tree being recorded (``with recorder.tree(x, y, sample) as t``). Rays are added
    under the current ray (``descend``/``ascend``) or under an explicit parent index."""

    def __init__(self, recorder: "Recorder", x: int, y: int, sample: int):
        self._recorder = recorder
        self.pixel = (int(x), int(y))
        self.sample = int(sample)
        self._rays: List[Tuple[int, Tuple[float, float, float], Tuple[float, float, float], float, str, int, Dict[str, Any]]] = []
        self._stack: List[int] = []
        self._last: Optional[int] = None
        self._ended = False
        #: Each ray's recording site (file, line, function), when the recorder records sites.
        self._sites: List[Tuple[str, int, str]] = []

    def add_ray(
        self,
        origin: Sequence[float],
        direction: Sequence[float],
        t: Optional[float],
        kind: str,
        prim: Optional[int] = None,
        parent: Optional[int] = None,
        **payload: Any,
    ) -> int:
        """Adds a ray (``t`` None: a miss); returns its index in the tree. Its parent is
        ``parent`` when given, else the ray the last ``descend`` went into (a root before)."""
        if self._ended:
            raise RecordError("this tree was already recorded: begin another with recorder.tree(...)")
        if parent is None:
            parent = self._stack[-1] if self._stack else -1
        elif not 0 <= parent < len(self._rays):
            raise RecordError(f"parent {parent} is not a ray of this tree (it has {len(self._rays)})")
        o = tuple(float(v) for v in origin)
        d = tuple(float(v) for v in direction)
        if len(o) != 3 or len(d) != 3:
            raise RecordError("origin and direction are three numbers each")
        self._rays.append((parent, o, d, float("nan") if t is None else float(t), kind, -1 if prim is None else int(prim), payload))  # type: ignore[arg-type]
        if self._recorder._sites:
            f = sys._getframe(1)
            self._sites.append((f.f_code.co_filename, f.f_lineno, f.f_code.co_name))
        self._last = len(self._rays) - 1
        return self._last

    def descend(self) -> None:
        """The next rays are children of the last one added."""
        if self._last is None:
            raise RecordError("descend: no ray was added yet")
        self._stack.append(self._last)

    def ascend(self) -> None:
        """Back to the parent level."""
        if not self._stack:
            raise RecordError("ascend: already at the root level")
        self._stack.pop()

    def end(self) -> int:
        """Records the tree now (a ``with`` block does so when it ends); returns its id in the
        dataset. Nothing can be added to it afterwards."""
        if self._ended:
            raise RecordError("this tree was already recorded")
        if not self._rays:
            raise RecordError("end: the tree has no rays")
        ids = self._recorder._add_trees([self])
        self._ended = True
        return ids[0]


class Recorder:
    """Records ray trees into a dataset directory (``Recorder(path, payload={...})``) or into
    memory (``Recorder.immediate(...)``). Payload columns are declared by type: ``"f32"``,
    ``"f32x3"`` (three per ray), ``"u32"``, ``"i64"``, ``"f64x4"``, ..."""

    def __init__(self, path: Optional[PathLike] = None, payload: Optional[Mapping[str, str]] = None, sites: bool = False, _native: Any = None):
        """``sites=True`` records each ray's site: the file, line and function of the Python
        code that added it (``t.add_ray``'s caller, or ``add_rays``'s), as the ``site`` column
        SQL shows as ``file:line function``. It costs a frame lookup per ray."""
        if _native is not None:
            self._native = _native
        else:
            if path is None:
                raise RecordError("Recorder(path): the dataset directory to write (or Recorder.immediate())")
            self._native = _rtvtk.NativeRecorder.create(os.fspath(path), list((payload or {}).items()), sites)
        self._payload = dict(self._native.payload())
        self._sites = bool(self._native.records_sites())
        self._closed = False

    @classmethod
    def immediate(cls, payload: Optional[Mapping[str, str]] = None, sites: bool = False) -> "Recorder":
        """An in-memory trace (queried while recording)."""
        return cls(_native=_rtvtk.NativeRecorder.immediate(list((payload or {}).items()), sites))

    @contextlib.contextmanager
    def tree(self, x: int, y: int, sample: int = 0) -> Iterator[Tree]:
        """A tree of pixel (x, y), recorded when the ``with`` block ends without an error."""
        t = Tree(self, x, y, sample)
        yield t
        if t._rays and not t._ended:
            self._add_trees([t])

    def _add_trees(self, trees: List[Tree]) -> List[int]:
        rays = [(i, r) for i, t in enumerate(trees) for r in t._rays]
        n = len(rays)
        if n == 0:
            return []
        kinds = sorted({r[4] for _, r in rays})
        code = {k: i for i, k in enumerate(kinds)}
        extra = {k for _, r in rays for k in r[6]} - set(self._payload)
        if extra:
            raise RecordError(f"payload {sorted(extra)[0]!r} was not declared when the recorder was made")
        payload = {}
        for name, spec in self._payload.items():
            dtype, width = _dtype(spec)
            missing = np.nan if dtype.kind == "f" else 0
            default = [missing] * width if width > 1 else missing
            try:
                values = np.asarray([r[6].get(name, default) for _, r in rays], dtype=dtype)
            except (TypeError, ValueError) as e:
                raise RecordError(f"payload {name!r} is declared {spec}: {e}") from None
            if values.shape != ((n, width) if width > 1 else (n,)):
                raise RecordError(f"payload {name!r} is declared {spec}: each ray needs {width} value(s)")
            payload[name] = values
        return self.add_rays(
            tree=np.asarray([i for i, _ in rays], dtype=np.int64),
            parent=np.asarray([r[0] for _, r in rays], dtype=np.int32),
            origin=np.asarray([r[1] for _, r in rays], dtype=np.float32),
            direction=np.asarray([r[2] for _, r in rays], dtype=np.float32),
            t=np.asarray([r[3] for _, r in rays], dtype=np.float32),
            kind=[kinds[code[r[4]]] for _, r in rays],
            pixel=np.asarray([trees[i].pixel for i, _ in rays], dtype=np.uint32),
            sample=np.asarray([trees[i].sample for i, _ in rays], dtype=np.uint32),
            prim=np.asarray([r[5] for _, r in rays], dtype=np.int64),
            _sites=[site for t in trees for site in t._sites] if self._sites else None,
            **payload,
        )

    def add_rays(
        self,
        tree: Any,
        parent: Any,
        origin: Any,
        direction: Any,
        t: Any,
        kind: Any,
        pixel: Any,
        sample: Any = None,
        prim: Any = None,
        site: Optional[Tuple[str, int, str]] = None,
        _sites: Optional[List[Tuple[str, int, str]]] = None,
        **payload: Any,
    ) -> List[int]:
        """Records whole trees from arrays (a wavefront renderer's batch). Rays of one tree are
        contiguous and share ``tree``; ``parent`` is each ray's parent index within its tree
        (-1 for a root); ``origin``/``direction`` are (n, 3); ``t`` NaN is a miss; ``kind`` is
        a sequence of kind names, or a ``(codes, names)`` pair of uint8 codes into names;
        ``pixel`` (n, 2) and ``sample`` of a tree are its first ray's; ``prim`` -1 is none.
        With ``sites=True`` the rays' site is ``site`` (file, line, function) or else this
        call's caller. Returns the dataset's id of each tree, in order."""
        self._check_open()
        tree = np.ascontiguousarray(tree, dtype=np.int64)
        n = tree.shape[0]
        if isinstance(kind, tuple) and len(kind) == 2:
            codes, names = np.ascontiguousarray(kind[0], dtype=np.uint8), [str(k) for k in kind[1]]
        else:
            names, inverse = np.unique(np.asarray(kind, dtype=object).astype(str), return_inverse=True)
            codes, names = np.ascontiguousarray(inverse, dtype=np.uint8), [str(k) for k in names]
        sample = np.zeros(n, dtype=np.uint32) if sample is None else sample
        prim = np.full(n, -1, dtype=np.int64) if prim is None else prim
        arrays = []
        for name, value in payload.items():
            spec = self._payload.get(name)
            if spec is None:
                raise RecordError(f"payload {name!r} was not declared when the recorder was made")
            dtype, _ = _dtype(spec)
            arr = np.asarray(value)
            if arr.dtype != dtype:
                raise RecordError(f"payload {name!r} is declared {spec}: expected {dtype.name} values, got {arr.dtype.name}")
            arrays.append((name, np.ascontiguousarray(arr)))
        site_codes, site_names = None, []
        if self._sites:
            if _sites is not None:
                index: Dict[Tuple[str, int, str], int] = {}
                per_ray = [index.setdefault(x, len(index)) for x in _sites]
                site_codes, site_names = np.asarray(per_ray, dtype=np.uint32), list(index)
            else:
                if site is None:
                    f = sys._getframe(1)
                    site = (f.f_code.co_filename, f.f_lineno, f.f_code.co_name)
                site_codes, site_names = np.zeros(n, dtype=np.uint32), [(str(site[0]), int(site[1]), str(site[2]))]
        return list(
            self._native.add_rays(
                tree,
                np.ascontiguousarray(parent, dtype=np.int32),
                np.ascontiguousarray(origin, dtype=np.float32),
                np.ascontiguousarray(direction, dtype=np.float32),
                np.ascontiguousarray(t, dtype=np.float32),
                codes,
                names,
                np.ascontiguousarray(pixel, dtype=np.uint32),
                np.ascontiguousarray(sample, dtype=np.uint32),
                np.ascontiguousarray(prim, dtype=np.int64),
                arrays,
                site_codes,
                site_names,
            )
        )

    def set_scene(
        self,
        vertices: Any,
        materials: Any,
        colors: Any,
        emission: Any,
        names: Optional[Sequence[str]] = None,
        point_lights: Optional[Tuple[Any, Any]] = None,
    ) -> None:
        """The scene's triangles so the viewer can draw it: ``vertices`` (n, 3, 3), ``materials``
        (n,) indices into the per-material ``colors`` and ``emission`` (m, 3). Emissive
        triangles and ``point_lights`` (``(positions, intensities)``, (k, 3) each) become the
        ``lights`` table (the paper's wrong-shadow query reads it)."""
        self._check_open()
        colors = np.ascontiguousarray(colors, dtype=np.float32)
        m = colors.shape[0] if colors.ndim > 1 else colors.size // 3
        names = list(names) if names is not None else [f"material{i}" for i in range(m)]
        points: Tuple[Any, Any] = (None, None)
        if point_lights is not None:
            positions, intensities = point_lights
            points = (np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3), np.ascontiguousarray(intensities, dtype=np.float32).reshape(-1, 3))
        self._native.set_triangles(
            np.ascontiguousarray(vertices, dtype=np.float32),
            np.ascontiguousarray(materials, dtype=np.uint32),
            colors,
            np.ascontiguousarray(emission, dtype=np.float32),
            names,
            points[0],
            points[1],
        )

    def set_camera(self, position: Sequence[float], target: Sequence[float], up: Sequence[float], fov_y: float, width: int, height: int) -> None:
        """The pinhole camera the rays were traced from (vertical field of view in degrees) and
        the image size."""
        self._check_open()
        self._native.set_camera(list(map(float, position)), list(map(float, target)), list(map(float, up)), float(fov_y), int(width), int(height))

    def set_image(self, rgb: Any) -> None:
        """The renderer's own picture of the recording, (height, width, 3) linear RGB: written
        beside the trace (``image.png`` tone mapped, ``image.exr`` linear) and shown by the
        image layer."""
        self._check_open()
        img = np.ascontiguousarray(rgb, dtype=np.float32)
        if img.ndim != 3 or img.shape[2] != 3:
            raise RecordError(f"set_image: expected (height, width, 3) RGB, got shape {img.shape}")
        self._native.set_image(int(img.shape[1]), int(img.shape[0]), img)

    def set_attributes(self, attributes: Mapping[str, str]) -> None:
        """Attributes of the recording (``{"image.png": "image.png"}`` names its picture)."""
        self._check_open()
        self._native.set_attributes([(str(k), str(v)) for k, v in attributes.items()])

    def flush(self) -> None:
        """Seals what was recorded so far (readable, crash-safe)."""
        self._check_open()
        self._native.flush()

    def finish(self) -> Dict[str, int]:
        """Ends the recording: trees, rays, segments and bytes written."""
        self._check_open()
        trees, rays, segments, nbytes = self._native.finish()
        self._closed = True
        return {"trees": trees, "rays": rays, "segments": segments, "bytes": nbytes}

    def session(self) -> "Session":
        """Immediate mode: SQL (and ``render``) over the trace in memory. Each query sees every
        ray recorded before it; tables written (``set_scene``) after the session was made
        appear in a new one."""
        return Session(self._native.session())

    def rays_recorded(self) -> int:
        """Immediate mode: rays recorded so far."""
        return int(self._native.immediate_rays())

    def _check_open(self) -> None:
        if self._closed:
            raise RecordError("the recorder is finished: nothing more can be recorded")

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if not self._closed:
            self.finish()


def _dtype(spec: str) -> Tuple[np.dtype, int]:
    base, _, width = spec.partition("x")
    return np.dtype({"f32": "float32", "f64": "float64", "i32": "int32", "i64": "int64", "u8": "uint8", "u16": "uint16", "u32": "uint32", "u64": "uint64"}[base]), int(width or 1)
