"""Type stubs of the rtvtk package (see the docstrings in __init__.py)."""

import os
from typing import Any, ContextManager, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import pyarrow as pa

__version__: str
KINDS: Tuple[str, ...]
PathLike = Union[str, os.PathLike[str]]

class Error(Exception):
    """An rtvtk call failed; the message says what and where."""

class DatasetError(Error):
    """A dataset could not be opened or read (path, manifest, files)."""

class QueryError(Error):
    """A query was refused or failed (SQL, tables, functions)."""

class RecordError(Error):
    """Recording input was refused (arrays, payload, scene, camera)."""

class RenderError(Error):
    """A picture or the viewer could not be made (layers, GPU, window)."""

class InternalError(Error):
    """rtvtk itself failed (a Rust panic): please report it."""

def open(datasets: Union[PathLike, Sequence[PathLike], Mapping[str, PathLike]]) -> Session: ...
def connect(url: str, token: Optional[str] = ...) -> Session: ...

class Picture:
    png: bytes
    report: List[str]
    def _repr_png_(self) -> bytes: ...
    def save(self, path: PathLike) -> None: ...
    @property
    def size(self) -> Tuple[int, int]: ...

class Report:
    markdown: str
    grids: Dict[str, Tuple[str, np.ndarray, int]]
    def save(self, directory: PathLike) -> str: ...
    def _repr_markdown_(self) -> str: ...

class Session:
    def sql(self, query: str, progress: bool = ...) -> pa.Table: ...
    def sql_batches(self, query: str) -> pa.RecordBatchReader: ...
    def tables(self) -> List[str]: ...
    def tree(self, tree_id: int) -> pa.Table: ...
    def trees_at_pixel(self, x: int, y: int, sample: Optional[int] = ...) -> pa.Table: ...
    def info(self, name: Optional[str] = ...) -> Dict[str, Any]: ...
    def check(self, name: Optional[str] = ...) -> List[str]: ...
    def analyze(self, analysis: str, progress: bool = ..., **options: Any) -> Report: ...
    def view(self, dataset: Optional[str] = ..., screenshot: Optional[PathLike] = ..., tracer: Optional[str] = ...) -> None: ...
    def queries_run(self) -> int: ...
    def render(
        self,
        progress: bool = ...,
        *,
        layers: Optional[Sequence[str]] = ...,
        sql: Optional[str] = ...,
        colour_by: Optional[str] = ...,
        tree: Optional[int] = ...,
        pixel: Optional[Tuple[int, int]] = ...,
        sample: Optional[int] = ...,
        kinds: Optional[Sequence[str]] = ...,
        depth: Optional[Tuple[int, int]] = ...,
        max_rays: Optional[int] = ...,
        bvh_levels: Optional[Tuple[int, int]] = ...,
        bvh_visited: bool = ...,
        geometry: str = ...,
        camera: Optional[Tuple[Tuple[float, float, float], Tuple[float, float, float], float]] = ...,
        size: Optional[Tuple[int, int]] = ...,
        line_width: float = ...,
        image_source: str = ...,
        image_spp: int = ...,
        legend: bool = ...,
    ) -> Picture: ...

class Tree:
    pixel: Tuple[int, int]
    sample: int
    def add_ray(
        self,
        origin: Sequence[float],
        direction: Sequence[float],
        t: Optional[float],
        kind: str,
        prim: Optional[int] = ...,
        parent: Optional[int] = ...,
        **payload: Any,
    ) -> int: ...
    def descend(self) -> None: ...
    def ascend(self) -> None: ...
    def end(self) -> int: ...

class Recorder:
    def __init__(self, path: Optional[PathLike] = ..., payload: Optional[Mapping[str, str]] = ..., sites: bool = ...) -> None: ...
    @classmethod
    def immediate(cls, payload: Optional[Mapping[str, str]] = ..., sites: bool = ...) -> Recorder: ...
    def tree(self, x: int, y: int, sample: int = ...) -> ContextManager[Tree]: ...
    def add_rays(
        self,
        tree: Any,
        parent: Any,
        origin: Any,
        direction: Any,
        t: Any,
        kind: Any,
        pixel: Any,
        sample: Any = ...,
        prim: Any = ...,
        site: Optional[Tuple[str, int, str]] = ...,
        **payload: np.ndarray,
    ) -> List[int]: ...
    def set_scene(
        self,
        vertices: Any,
        materials: Any,
        colors: Any,
        emission: Any,
        names: Optional[Sequence[str]] = ...,
        point_lights: Optional[Tuple[Any, Any]] = ...,
    ) -> None: ...
    def set_camera(self, position: Sequence[float], target: Sequence[float], up: Sequence[float], fov_y: float, width: int, height: int) -> None: ...
    def set_image(self, rgb: Any) -> None: ...
    def set_attributes(self, attributes: Mapping[str, str]) -> None: ...
    def flush(self) -> None: ...
    def finish(self) -> Dict[str, int]: ...
    def session(self) -> Session: ...
    def rays_recorded(self) -> int: ...
    def __enter__(self) -> Recorder: ...
    def __exit__(self, *args: Any) -> None: ...
