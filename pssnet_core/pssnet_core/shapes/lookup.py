"""One lookup from any object identity to its :class:`Shape`, whichever generator or source made it.

Datasets store identities (``"mug-00042"``, ``"imug-2000003"``, ``"rmug-00000"``); evaluation code rebuilds the
meshes from them with :func:`shape_of` and never needs to know the generator. The family groups say which
families the experiments treat alike: mugs (a handle the ambiguity measure can turn) and boxes (a hidden extent it
can stretch).
"""

from __future__ import annotations

from pssnet_core.shapes.independent import INDEPENDENT_FAMILIES, make_independent_shape
from pssnet_core.shapes.procedural import FAMILIES, Shape, ShapeError, ShapeId, make_shape
from pssnet_core.shapes.registry_objects import REGISTRY_FAMILIES, load_registry_shape

ALL_FAMILIES: tuple[str, ...] = FAMILIES + INDEPENDENT_FAMILIES + REGISTRY_FAMILIES
"""Every family an identity may name."""

MUG_FAMILIES: tuple[str, ...] = ("mug", "imug", "rmug", "mug_broad")
"""Mugs of every source: ``Shape.handle`` is set when the mug has a handle."""

BOX_FAMILIES: tuple[str, ...] = ("box", "ibox", "rbox", "box_broad", "box_edged")
"""Boxes of every source: the slit experiment stretches them along their hidden axis."""


def shape_of(identity: str | ShapeId) -> Shape:
    """The Shape of an identity (procedural, independent or registry object).

    Registry objects are read from the archive cache and fetched into it first if needed (see
    :mod:`pssnet_core.shapes.registry_objects`).

    Raises:
        ShapeError: not an identity, or an unknown family or seed.
        RegistryObjectError: a registry object that cannot be fetched or read.
    """
    sid = identity if isinstance(identity, ShapeId) else ShapeId.parse(identity)
    if sid.family in FAMILIES:
        return make_shape(sid.family, sid.seed)
    if sid.family in INDEPENDENT_FAMILIES:
        return make_independent_shape(sid.family, sid.seed)
    if sid.family in REGISTRY_FAMILIES:
        return load_registry_shape(sid.family, sid.seed)
    raise ShapeError(f"unknown family {sid.family!r} in {str(identity)!r}; expected one of {ALL_FAMILIES}")
