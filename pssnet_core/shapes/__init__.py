"""Object shapes: procedural families (mugs, YCB-like objects) and a loader for a user's own mesh folders."""

from pssnet_core.shapes.mesh_io import (
    LAYOUTS,
    MeshLoadError,
    export_shapes,
    load_mesh,
    load_mesh_folder,
    normalize_mesh,
)
from pssnet_core.shapes.procedural import (
    BROAD_FAMILIES,
    FAMILIES,
    MAX_DIAGONAL,
    SPLIT_RANGES,
    YCB_FAMILIES,
    Shape,
    ShapeError,
    ShapeId,
    make_shape,
    split_of_seed,
    split_seeds,
)

__all__ = [
    "BROAD_FAMILIES", "FAMILIES", "LAYOUTS", "MAX_DIAGONAL", "SPLIT_RANGES", "YCB_FAMILIES", "MeshLoadError", "Shape",
    "ShapeError", "ShapeId", "export_shapes", "load_mesh", "load_mesh_folder", "make_shape", "normalize_mesh",
    "split_of_seed", "split_seeds",
]
