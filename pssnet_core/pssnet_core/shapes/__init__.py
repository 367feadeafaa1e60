"""Object shapes: procedural families (mugs, YCB-like objects), an independent out-of-family generator, real
modelled objects from registry packages, one lookup from identity to shape, and a loader for a user's own mesh
folders."""

from pssnet_core.shapes.independent import INDEPENDENT_FAMILIES, make_independent_shape
from pssnet_core.shapes.lookup import ALL_FAMILIES, BOX_FAMILIES, MUG_FAMILIES, shape_of
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
    EDGED_FAMILIES,
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
from pssnet_core.shapes.registry_objects import REGISTRY_FAMILIES, RegistryObjectError

__all__ = [
    "ALL_FAMILIES", "BOX_FAMILIES", "BROAD_FAMILIES", "EDGED_FAMILIES", "FAMILIES", "INDEPENDENT_FAMILIES", "LAYOUTS",
    "MAX_DIAGONAL", "MUG_FAMILIES", "REGISTRY_FAMILIES", "SPLIT_RANGES", "YCB_FAMILIES", "MeshLoadError",
    "RegistryObjectError", "Shape", "ShapeError", "ShapeId", "export_shapes", "load_mesh", "load_mesh_folder",
    "make_independent_shape", "make_shape", "normalize_mesh", "shape_of", "split_of_seed", "split_seeds",
]
