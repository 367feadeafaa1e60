"""Dataset specifications (mugs, ycb, ycb_narrow, ycb_wide) and the making of one sample.

A dataset is a list of ``num_objects * views`` samples; sample ``index`` shows object ``index // views``
in view ``index % views``. Everything random about a sample comes from its own generator, seeded by
``(seed, stream, index)``, so any sample can be made alone, in any process, in any order, with the same
result; ``ycb_narrow`` and ``ycb_wide`` share a stream, hence the same objects, poses and cameras, and differ
only in the slit.

The experiments (DESIGN.md, paper Sec. 5):

* ``mugs``: each mug turned about the vertical in ``360 / views`` degree steps (72 views: 5 degrees);
  a fresh camera (distance 0.5-1.0 m, looking down 0-45 degrees, aim jitter 1 cm) for every view, always
  from the same side (azimuth 180 degrees), so the yaw alone decides where the handle points. No slit.
* ``ycb`` (train): 24 rotations per object (12 yaws 30 degrees apart, plus a random per-object offset,
  standing upright and tipped 90 degrees about a horizontal axis), a random translation on the plane
  (within +-5 cm), a fresh camera per view, and a vertical slit 3-18 cm wide at the object whose centre lies
  within +-10 % of the object's visible width from its centre (wider offsets push the grid, which is
  centred sideways on what is seen, off the object: 25 % clipped 4 % of the views sideways).
* ``ycb_narrow`` / ``ycb_wide`` (test): the same 24 rotations, each seen through a fixed slit (3.6 cm / 18 cm)
  at three translations of the object across the slit (-1, 0, +1 cm, limited to a quarter of the object's
  visible width so that the slit always stays over the object's central part): 72 views per object.
* ``mugs_narrow`` (test, built with ``mugs``): the very views of ``mugs`` (same stream) seen through the narrow
  slit (3.6 cm, centred on the mug), so that what the slit alone does to a completion is paired view by view;
  ``oof_mugs_narrow`` likewise for ``oof_mugs``. The default and ``large`` training sets (the shipped model's) show
  no mug behind a slit.
* ``oof_mugs``, ``oof_narrow``, ``oof_wide`` (test only, ``--family oof``): the out-of-family test sets, objects the
  training data never sees: mugs of the independent generator (:mod:`pssnet_core.shapes.independent`) and real
  modelled mugs (:mod:`pssnet_core.shapes.registry_objects`) turned like ``mugs`` in 15 degree steps; independent
  and real boxes, cans and bottles behind the same fixed slits as ``ycb_narrow`` / ``ycb_wide``, 24 rotations each,
  centred on the slit. Same cameras as every other set. ``--num-objects N`` keeps the first N objects of a set
  (the independent ones come first, so a small set needs no registry download).
* ``--scale large`` (train only): many objects, few views each (20,000 mugs and 20,000 ycb objects x 4
  views = 160,000 views). With 4 views the fixed yaw steps above would show every object from the same few
  sides, so each view draws its yaw uniformly in [0, 360) (``random_yaw``; ycb: every other view tipped 90
  degrees), and Kinect-like noise is on for half of the views (``noise_fraction``). Why: with a few hundred
  objects the encoder recognises a training object from its visible side and recalls its hidden side, so
  the posterior learns little of the ambiguity; objects here are as cheap as views.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from pssnet_core.data import SCALES
from pssnet_core.data.scenes import (
    CROP_MARGIN_PX,
    ObjectScene,
    RenderedView,
    SceneError,
    SensorNoise,
    Slit,
    box_in_grid,
    crop_window,
    object_pose,
    orbit_camera,
    posed_box_corners,
)
from pssnet_core.geometry import CameraIntrinsics, GridConfig, ObservationError
from pssnet_core.shapes import EDGED_FAMILIES, MUG_FAMILIES, YCB_FAMILIES, Shape, ShapeId, shape_of, split_seeds
from pssnet_core.shapes.registry_objects import registry_identities

MUG_VIEWS = 72
YCB_ROTATIONS = 24
YCB_TRANSLATION_STEPS = (-1, 0, 1)
NARROW_SLIT_M = 0.036
WIDE_SLIT_M = 0.18
SLIT_MODES = ("none", "random", "fixed")
DATASET_NAMES = ("mugs", "mugs_narrow", "ycb", "ycb_narrow", "ycb_wide", "oof_mugs", "oof_mugs_narrow", "oof_narrow",
                 "oof_wide")
FAMILY_CHOICES = ("mugs", "ycb", "all", "oof")
# The out-of-family test sets (objects per source; evaluation cost grows with the square of a set's views).
OOF_MUG_VIEWS = 24
OOF_INDEPENDENT_MUGS = 16
OOF_INDEPENDENT_SLIT: dict[str, int] = {"ibox": 10, "ican": 3, "ibottle": 3}
MAX_ATTEMPTS = 20

# Default object counts: `--family all --split train` gives 120 * 72 + 300 * 24 = 15,840 samples; every
# test set has 12 objects * 72 views = 864 samples (evaluation is quadratic in the test-set size).
DEFAULT_OBJECTS: dict[tuple[str, str], int] = {
    ("mugs", "train"): 120, ("ycb", "train"): 300,
    ("mugs", "test"): 12, ("ycb_narrow", "test"): 12, ("ycb_wide", "test"): 12,
    ("mugs", "val"): 6, ("ycb", "val"): 16,
}
SLIT_MUG_FRACTION = 0.5  # --scale slits: mug views behind the ycb objects' random slits
BROAD_MUG_SLIT_M = (0.03, 0.3)  # broad mugs: a random slit, wider than the mug in about two views of three
LARGE_TRAIN_OBJECTS = 20_000  # per family group (mugs; ycb), see the module docstring
LARGE_TRAIN_VIEWS = 4
LARGE_NOISE_FRACTION = 0.5
LARGE_OBJECTS_PER_SHARD = 32  # 128 views a shard: training mixes two shards, so a batch spans ~64 objects


class DatasetSpecError(ValueError):
    """A dataset specification or build request is invalid; the message says which part."""


@dataclass(frozen=True)
class DatasetSpec:
    """Everything that determines a dataset's samples (stored in its index as ``meta["spec"]``).

    Attributes:
        name: "mugs", "ycb", "ycb_narrow" or "ycb_wide".
        split: "train" or "test" (object seeds come from :func:`split_seeds`, disjoint by identity).
        families: object families, cycled over the objects (object i has family ``families[i % len]``).
        num_objects: number of objects.
        views: views per object (mugs: yaw steps of 360/views degrees; ycb: evenly spread over the
            rotation x translation combinations, 24 for training and 72 for the test sets).
        grid_size: observation grid voxels per edge (the grid always spans 0.20 m).
        front_margin: grid placement margin in front of the nearest observed point (voxels); the node must
            use the same value (it is stored in the dataset's meta as ``grid_config``).
        bottom_margin: grid placement margin below the lowest observed point (voxels), likewise.
        seed: master seed.
        stream: name of the random stream (defaults to ``name``); datasets sharing it share poses.
        slit_mode: "none", "random" (train: width in ``slit_range_m``) or "fixed" (``slit_width_m``).
        slit_width_m: fixed slit width (m).
        slit_range_m: range of the random slit width (m).
        slit_offset_fraction: random slit centre within +- this fraction of the object's visible width.
        slit_fraction: share of the views seen through the random slit (drawn per view from a stream of its own,
            so that the other views' cameras are those of the same spec without a slit; 1.0 = all).
        translation_step_m: fixed-slit test sets: step of the object's translation across the slit (m).
        translations: number of translation steps in fixed-slit test sets (views per rotation).
        ycb_translation_m: training translation of ycb objects on the plane, uniform in +- this (m).
        distance_range_m: camera distance from the aim point (m).
        tilt_range_deg: camera looking down this many degrees.
        aim_jitter_m: the camera aims at the object's box centre plus a uniform offset within +- this (m).
        objects_per_shard: objects per shard (the unit of parallel work and of resuming).
        noise: sensor imperfections, or None for exact depth (the default; ground truth is always exact).
        noise_fraction: share of the views that get ``noise`` (drawn per view; 1.0 = all).
        random_yaw: each view draws the object's yaw uniformly in [0, 360) instead of the fixed steps
            (ycb: tipped 90 degrees on odd views); for datasets of many objects with few views each.
        image_width: image width (pixels; Kinect-like intrinsics scaled to it).
        image_height: image height (pixels).
        identities: the objects by identity, in order (then ``num_objects`` must equal their number and
            ``families`` name their families); empty: ``families`` cycled over the split's seeds.
    """

    name: str
    split: str
    families: tuple[str, ...]
    num_objects: int
    views: int
    grid_size: int = 32
    front_margin: float = GridConfig.front_margin
    bottom_margin: float = GridConfig.bottom_margin
    seed: int = 0
    stream: str = ""
    slit_mode: str = "none"
    slit_width_m: float | None = None
    slit_range_m: tuple[float, float] = (0.03, 0.18)
    slit_offset_fraction: float = 0.1
    slit_fraction: float = 1.0
    translation_step_m: float = 0.01
    translations: int = 1
    ycb_translation_m: float = 0.05
    distance_range_m: tuple[float, float] = (0.5, 1.0)
    tilt_range_deg: tuple[float, float] = (0.0, 45.0)
    aim_jitter_m: float = 0.01
    objects_per_shard: int = 4
    noise: SensorNoise | None = None
    noise_fraction: float = 1.0
    random_yaw: bool = False
    image_width: int = 640
    image_height: int = 480
    identities: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.split not in ("train", "val", "test"):
            raise DatasetSpecError(f"split must be train, val or test, got {self.split!r}")
        if self.num_objects < 1 or self.views < 1 or self.objects_per_shard < 1:
            raise DatasetSpecError(
                f"num_objects, views and objects_per_shard must be >= 1, got {self.num_objects}, {self.views}, "
                f"{self.objects_per_shard}")
        if self.slit_mode not in SLIT_MODES:
            raise DatasetSpecError(f"slit_mode must be one of {SLIT_MODES}, got {self.slit_mode!r}")
        if self.slit_mode == "fixed" and not (self.slit_width_m and self.slit_width_m > 0):
            raise DatasetSpecError("a fixed slit needs a positive slit_width_m")
        if not 0.0 <= self.noise_fraction <= 1.0:
            raise DatasetSpecError(f"noise_fraction must lie in [0, 1], got {self.noise_fraction}")
        if not 0.0 <= self.slit_fraction <= 1.0:
            raise DatasetSpecError(f"slit_fraction must lie in [0, 1], got {self.slit_fraction}")
        if not self.is_mugs and not self.random_yaw and self.views > self.combinations:
            raise DatasetSpecError(
                f"{self.name} has {self.combinations} rotation/translation combinations per object; "
                f"views must be at most that, got {self.views}")
        if not 0 <= self.tilt_range_deg[0] <= self.tilt_range_deg[1] < 80:
            raise DatasetSpecError(f"tilt range must lie in [0, 80) degrees, got {self.tilt_range_deg}")
        if not 0 < self.distance_range_m[0] <= self.distance_range_m[1]:
            raise DatasetSpecError(f"distance range must be positive and ordered, got {self.distance_range_m}")
        if self.identities:
            if len(self.identities) != self.num_objects:
                raise DatasetSpecError(f"{len(self.identities)} identities for {self.num_objects} objects")
            families = {ShapeId.parse(i).family for i in self.identities}
            if families != set(self.families):
                raise DatasetSpecError(f"families {self.families} do not match the identities' {sorted(families)}")
        _ = self.grid_config  # validates size and margins

    @property
    def is_mugs(self) -> bool:
        """Mug experiment (yaw steps or random yaw): every family is a mug family."""
        return all(f in MUG_FAMILIES for f in self.families)

    @property
    def combinations(self) -> int:
        """Distinct (rotation, translation) views per object for the ycb datasets."""
        return YCB_ROTATIONS * max(self.translations, 1)

    @property
    def num_samples(self) -> int:
        return self.num_objects * self.views

    @property
    def num_shards(self) -> int:
        return math.ceil(self.num_objects / self.objects_per_shard)

    @property
    def grid_config(self) -> GridConfig:
        base = GridConfig.for_size(self.grid_size)
        return replace(base, front_margin=float(self.front_margin), bottom_margin=float(self.bottom_margin))

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return CameraIntrinsics.kinect_like(self.image_width, self.image_height)

    def shard_range(self, shard: int) -> range:
        """Sample indices of shard ``shard``."""
        if not 0 <= shard < self.num_shards:
            raise DatasetSpecError(f"shard {shard} out of range for {self.num_shards} shards")
        first = shard * self.objects_per_shard
        last = min(first + self.objects_per_shard, self.num_objects)
        return range(first * self.views, last * self.views)

    def object_identities(self) -> list[ShapeId]:
        """Identity of every object, in order."""
        if self.identities:
            return [ShapeId.parse(i) for i in self.identities]
        seeds = split_seeds(self.split, self.num_objects)
        return [ShapeId(self.families[i % len(self.families)], seed) for i, seed in enumerate(seeds)]

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (JSON)."""
        data = asdict(self)
        data["families"] = list(self.families)
        data["noise"] = None if self.noise is None else asdict(self.noise)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DatasetSpec:
        """Inverse of :meth:`to_dict`."""
        data = dict(data)
        data["families"] = tuple(data["families"])
        data["identities"] = tuple(data.get("identities", ()))
        for key in ("slit_range_m", "distance_range_m", "tilt_range_deg"):
            data[key] = tuple(data[key])
        data["noise"] = None if data.get("noise") is None else SensorNoise(**data["noise"])
        return cls(**data)


def dataset_specs(family: str, split: str, grid_size: int = 32, seed: int = 0, num_objects: int | None = None,
                  views: int | None = None, noise: SensorNoise | None = None,
                  front_margin: float | None = None, bottom_margin: float | None = None,
                  scale: str = "default", slit_fraction: float | None = None) -> list[DatasetSpec]:
    """The datasets of an experiment family and split.

    Args:
        family: "mugs", "ycb", "all" or "oof" (the out-of-family test sets; test split only).
        split: "train", "val" or "test"; "val" is built like "train" (random slits) from its own objects, to
            validate during training; the ycb test split is two datasets, ``ycb_narrow`` and ``ycb_wide``.
        grid_size: voxels per grid edge (32 or 64 in the paper's experiments).
        seed: master seed.
        num_objects: overrides the default number of objects of every dataset.
        views: overrides the number of views per object.
        noise: sensor imperfections (None: exact depth).
        front_margin: grid placement margin override (voxels; default GridConfig's).
        bottom_margin: grid placement margin override (voxels; default GridConfig's).
        scale: "default", "large" (train: 20,000 objects per family group x 4 random-yaw views, noise on
            half of the views unless ``noise`` is given) or "broad" (as large, with half the objects from
            :data:`~pssnet_core.shapes.procedural.BROAD_FAMILIES`, and the mugs seen through random slits too,
            so that a hidden handle can lie at any azimuth) or "boxes" (as large, with the ycb group joined by
            boxes of independent sides, ``box_broad``, and of bevelled or rounded edges,
            :data:`~pssnet_core.shapes.procedural.EDGED_FAMILIES`: 3 of 7 objects are boxes, not 1 of 5, the
            mugs as in large) or "slits" (as large, with half the mugs' views seen through the random slits of the
            ycb objects, so that a slit no longer tells a model the object is not a mug); val and test are the
            same at every scale, so that
            models trained at any scale are validated and tested alike.
        slit_fraction: with scale "slits" and the train split only: the share of the mug views seen through a
            slit (default :data:`SLIT_MUG_FRACTION`).
    """
    if scale not in SCALES:
        raise DatasetSpecError(f"scale must be one of {SCALES}, got {scale!r}")
    if family not in FAMILY_CHOICES:
        raise DatasetSpecError(f"family must be one of {FAMILY_CHOICES}, got {family!r}")
    if split not in ("train", "val", "test"):
        raise DatasetSpecError(f"split must be train, val or test, got {split!r}")
    if family == "oof" and split != "test":
        raise DatasetSpecError("the out-of-family sets (--family oof) are test sets only: use --split test")
    if slit_fraction is not None and (scale != "slits" or split != "train"):
        raise DatasetSpecError("a slit fraction belongs to --scale slits and the train split only")
    common: dict[str, Any] = {"split": split, "grid_size": grid_size, "seed": seed, "noise": noise}
    if front_margin is not None:
        common["front_margin"] = float(front_margin)
    if bottom_margin is not None:
        common["bottom_margin"] = float(bottom_margin)
    specs: list[DatasetSpec] = []
    if family in ("mugs", "all"):
        specs.append(DatasetSpec(name="mugs", families=("mug",), views=MUG_VIEWS,
                                 num_objects=DEFAULT_OBJECTS[("mugs", split)], objects_per_shard=4, **common))
        if split == "test":
            specs.append(_behind_narrow_slit(specs[-1]))
    if family in ("ycb", "all"):
        if split in ("train", "val"):
            specs.append(DatasetSpec(name="ycb", families=YCB_FAMILIES, views=YCB_ROTATIONS, slit_mode="random",
                                     num_objects=DEFAULT_OBJECTS[("ycb", split)], objects_per_shard=12, **common))
        else:
            for name, width in (("ycb_narrow", NARROW_SLIT_M), ("ycb_wide", WIDE_SLIT_M)):
                specs.append(DatasetSpec(
                    name=name, families=YCB_FAMILIES, stream="ycb_test", slit_mode="fixed", slit_width_m=width,
                    translations=len(YCB_TRANSLATION_STEPS), views=YCB_ROTATIONS * len(YCB_TRANSLATION_STEPS),
                    ycb_translation_m=0.0, num_objects=DEFAULT_OBJECTS[(name, split)], objects_per_shard=4,
                    **common))
    if family == "oof":
        specs += _oof_specs(common, num_objects)
        num_objects = None  # applied to the identity lists
    overrides: dict[str, Any] = {}
    if scale in ("large", "broad", "boxes", "slits") and split == "train":
        overrides.update(num_objects=LARGE_TRAIN_OBJECTS, views=LARGE_TRAIN_VIEWS, random_yaw=True,
                         objects_per_shard=LARGE_OBJECTS_PER_SHARD)
        if noise is None:
            overrides.update(noise=SensorNoise(), noise_fraction=LARGE_NOISE_FRACTION)
    if scale == "broad" and split == "train":
        specs = [replace(s, families=("mug", "mug_broad"), slit_mode="random", slit_range_m=BROAD_MUG_SLIT_M)
                 if s.is_mugs else replace(s, families=YCB_FAMILIES + ("box_broad", "can_broad", "bottle_broad"))
                 for s in specs]
    if scale == "slits" and split == "train":
        fraction = SLIT_MUG_FRACTION if slit_fraction is None else float(slit_fraction)
        specs = [replace(s, slit_mode="random", slit_fraction=fraction) if s.is_mugs else s for s in specs]
    if scale == "boxes" and split == "train":
        specs = [s if s.is_mugs else replace(s, families=YCB_FAMILIES + ("box_broad",) + EDGED_FAMILIES)
                 for s in specs]
    if num_objects is not None:
        overrides["num_objects"] = int(num_objects)
    if views is not None:
        overrides["views"] = int(views)
    return [replace(s, **overrides) for s in specs] if overrides else specs


def _oof_specs(common: dict[str, Any], num_objects: int | None) -> list[DatasetSpec]:
    """``oof_mugs``, ``oof_narrow`` and ``oof_wide``: independent objects first, then the registry's."""
    test_seeds = split_seeds("test", max(OOF_INDEPENDENT_MUGS, *OOF_INDEPENDENT_SLIT.values()))
    real = registry_identities()
    mugs = [str(ShapeId("imug", s)) for s in test_seeds[:OOF_INDEPENDENT_MUGS]]
    mugs += [str(i) for i in real if i.family in MUG_FAMILIES]
    slit = [str(ShapeId(f, s)) for f, n in OOF_INDEPENDENT_SLIT.items() for s in test_seeds[:n]]
    slit += [str(i) for i in real if i.family not in MUG_FAMILIES]

    def spec(name: str, identities: list[str], **kwargs: Any) -> DatasetSpec:
        chosen = tuple(identities[:num_objects] if num_objects is not None else identities)
        if not chosen:
            raise DatasetSpecError(f"num_objects must be >= 1, got {num_objects}")
        families = tuple(dict.fromkeys(ShapeId.parse(i).family for i in chosen))
        return DatasetSpec(name=name, families=families, identities=chosen, num_objects=len(chosen),
                           objects_per_shard=4, **kwargs, **common)

    out = [spec("oof_mugs", mugs, views=OOF_MUG_VIEWS)]
    out.append(_behind_narrow_slit(out[0]))
    for name, width in (("oof_narrow", NARROW_SLIT_M), ("oof_wide", WIDE_SLIT_M)):
        out.append(spec(name, slit, stream="oof_slit_test", slit_mode="fixed", slit_width_m=width, translations=1,
                        views=YCB_ROTATIONS, ycb_translation_m=0.0))
    return out


def _behind_narrow_slit(mugs: DatasetSpec) -> DatasetSpec:
    """A mug test set's very views (same stream: objects, turns, cameras) seen through the narrow slit.

    Why: the shipped model's training data (``--scale large``) shows mugs only in the open and YCB-like objects only
    behind a slit, so a slit alone can tell a model "not a mug"; a mug between two other objects breaks that habit,
    and the paired views say what the slit alone costs.
    """
    return replace(mugs, name=f"{mugs.name}_narrow", stream=mugs.stream or mugs.name, slit_mode="fixed",
                   slit_width_m=NARROW_SLIT_M)


# ---------------------------------------------------------------------------------------------- samples


def _rng(spec: DatasetSpec, *key: int) -> np.random.Generator:
    stream = zlib.crc32(f"{spec.stream or spec.name}/{spec.split}".encode())
    return np.random.default_rng([int(spec.seed), stream, *key])


@dataclass(frozen=True)
class ViewPlan:
    """The drawn parameters of one sample's view (recorded with the sample)."""

    yaw_deg: float
    tip_deg: float
    translation: tuple[float, float]
    distance_m: float
    tilt_deg: float
    aim_offset: tuple[float, float, float]
    slit: Slit | None
    noise_seed: int
    translation_step: int | None
    noisy: bool


def plan_view(spec: DatasetSpec, index: int, attempt: int = 0) -> ViewPlan:
    """Draws the view parameters of sample ``index`` (attempt > 0: a redraw after an unusable view)."""
    obj, view = divmod(index, spec.views)
    rng = _rng(spec, 0, index, attempt)
    step = None
    # Draws added after the first datasets were built use their own stream, so those datasets stay the same.
    extra = _rng(spec, 2, index, attempt)
    if spec.is_mugs:
        yaw = float(extra.uniform(0.0, 360.0)) if spec.random_yaw else view * 360.0 / spec.views
        tip, translation = 0.0, (0.0, 0.0)
    else:
        combo = view * spec.combinations // spec.views
        rotation, step_index = divmod(combo, max(spec.translations, 1))
        yaw_offset = float(_rng(spec, 1, obj).uniform(0.0, 30.0))  # per object, same for all its views
        if spec.random_yaw:
            yaw, tip = float(extra.uniform(0.0, 360.0)), 90.0 * (view % 2)
        else:
            yaw = (rotation % 12) * 30.0 + yaw_offset
            tip = 90.0 * (rotation // 12)
        t = spec.ycb_translation_m
        translation = tuple(float(x) for x in rng.uniform(-t, t, size=2)) if t > 0 else (0.0, 0.0)
        if spec.slit_mode == "fixed":
            steps = YCB_TRANSLATION_STEPS if spec.translations == len(YCB_TRANSLATION_STEPS) else \
                tuple(range(-(spec.translations // 2), spec.translations - spec.translations // 2))
            step = int(steps[step_index])
    slit = None
    if spec.slit_mode == "random":
        # A slit on only some views draws from a stream of its own: the camera draws below stay those without it.
        partial = spec.slit_fraction < 1.0
        draws = _rng(spec, 3, index, attempt) if partial else rng
        if not partial or draws.random() < spec.slit_fraction:
            slit = Slit(width_m=float(draws.uniform(*spec.slit_range_m)),
                        offset_fraction=float(draws.uniform(-spec.slit_offset_fraction, spec.slit_offset_fraction)))
    elif spec.slit_mode == "fixed":
        # The object moves across the fixed slit: equivalently the slit moves the other way over the object.
        slit = Slit(width_m=float(spec.slit_width_m), offset_m=-(step or 0) * spec.translation_step_m,
                    max_offset_fraction=0.25)
    return ViewPlan(
        yaw_deg=float(yaw), tip_deg=float(tip), translation=translation,
        distance_m=float(rng.uniform(*spec.distance_range_m)), tilt_deg=float(rng.uniform(*spec.tilt_range_deg)),
        aim_offset=tuple(float(x) for x in rng.uniform(-spec.aim_jitter_m, spec.aim_jitter_m, size=3)),
        slit=slit, noise_seed=int(rng.integers(2**31)), translation_step=step,
        noisy=spec.noise is not None and (spec.noise_fraction >= 1.0 or extra.random() < spec.noise_fraction))


def make_sample(spec: DatasetSpec, index: int, scene: ObjectScene) -> dict[str, Any]:
    """Renders and observes sample ``index`` of ``spec``; ``scene`` must hold that sample's object.

    Returns:
        The sample dict written to a shard: arrays ``known_occupied``, ``known_free``, ``occupancy``
        (bool N^3), ``box`` ((24,) float32 grid coordinates), ``depth`` (uint16 mm crop), ``mask`` (uint8
        crop) and the record fields documented in the data README.

    Raises:
        DatasetSpecError: no usable view after :data:`MAX_ATTEMPTS` draws (a bug in the spec's ranges).
    """
    shape = scene.shape
    obj, view_index = divmod(index, spec.views)
    config = spec.grid_config
    intrinsics = spec.intrinsics
    last_error: Exception | None = None
    for attempt in range(MAX_ATTEMPTS):
        plan = plan_view(spec, index, attempt)
        pose = object_pose(shape.mesh, plan.yaw_deg, plan.tip_deg, plan.translation)
        target = posed_box_corners(shape, pose).mean(axis=0) + np.asarray(plan.aim_offset)
        camera = orbit_camera(target, plan.distance_m, plan.tilt_deg)
        try:
            view = scene.render(pose, camera, intrinsics, slit=plan.slit, noise=spec.noise if plan.noisy else None,
                                noise_seed=plan.noise_seed)
            obs = view.observe(config)
        except (SceneError, ObservationError) as error:  # e.g. too few pixels left in a slit: redraw
            last_error = error
            continue
        break
    else:
        raise DatasetSpecError(f"sample {index} of {spec.name}: no usable view in {MAX_ATTEMPTS} draws "
                               f"(last error: {last_error})")
    occupancy = scene.ground_truth(pose, obs.pose, camera)
    overshoot = scene.grid_overshoot(pose, obs.pose, camera)
    v0, u0, v1, u1 = crop_window(view, obs.pose)
    depth_mm = np.rint(view.depth[v0:v1, u0:u1].astype(np.float64) * 1000.0).astype(np.uint16)
    return {
        "known_occupied": obs.known_occupied,
        "known_free": obs.known_free,
        "occupancy": occupancy,
        "box": box_in_grid(shape, pose, obs.pose, camera),
        "depth": depth_mm,
        "mask": view.mask[v0:v1, u0:u1].copy(),
        "index": int(index),
        "dataset": spec.name,
        "split": spec.split,
        "identity": str(shape.identity),
        "family": shape.identity.family,
        "seed": int(shape.identity.seed),
        "object_index": int(obj),
        "view": int(view_index),
        "rotation_deg": plan.yaw_deg,
        "tip_deg": plan.tip_deg,
        "translation": list(plan.translation),
        "translation_step": plan.translation_step,
        "distance_m": plan.distance_m,
        "tilt_deg": plan.tilt_deg,
        "object_pose": pose.tolist(),
        "camera_pose": camera.tolist(),
        "intrinsics": asdict(intrinsics),
        "up": view.up.tolist(),
        "grid_pose": obs.pose.to_dict(),
        "handle_visible": view.handle_visible,
        "handle_area_m2": view.handle_area_m2,
        "has_handle": shape.handle is not None if shape.identity.family in MUG_FAMILIES else None,
        "slit_width_m": None if plan.slit is None else plan.slit.width_m,
        "slit_columns": None if view.slit_columns is None else list(view.slit_columns),
        "noise": asdict(spec.noise) if plan.noisy else None,
        "noise_seed": plan.noise_seed,
        "attempts": attempt + 1,
        "crop": [v0, u0],
        "image_size": [intrinsics.height, intrinsics.width],
        "clipped": bool(overshoot > 0.5),
        "overshoot_voxels": overshoot,
        "occupied_voxels": int(occupancy.sum()),
    }


def full_images(sample: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Rebuilds the full-size depth (float32 metres, 0 = no reading) and mask (uint8) of a stored sample.

    The stored crop covers the mask and the projection of the whole observation grid plus the
    free-space carving footprint (:data:`pssnet_core.data.scenes.CROP_MARGIN_PX`), so
    ``observe(depth, mask, ...)`` on the rebuilt images gives exactly the stored grids. Pixels outside the
    crop read 0 (no reading); re-render with :func:`rerender` for the plane around them.
    """
    height, width = sample["image_size"]
    v0, u0 = sample["crop"]
    crop_depth = np.asarray(sample["depth"])
    crop_mask = np.asarray(sample["mask"])
    h, w = crop_depth.shape
    depth = np.zeros((height, width), dtype=np.float32)
    mask = np.zeros((height, width), dtype=np.uint8)
    depth[v0:v0 + h, u0:u0 + w] = (crop_depth.astype(np.float64) / 1000.0).astype(np.float32)
    mask[v0:v0 + h, u0:u0 + w] = crop_mask
    return depth, mask


def sample_intrinsics(sample: dict[str, Any]) -> CameraIntrinsics:
    """The stored intrinsics of a sample."""
    return CameraIntrinsics(**sample["intrinsics"])


def rerender(sample: dict[str, Any], shape: Shape | None = None) -> RenderedView:
    """Renders a stored sample's view again (whole image) from its record: same pose, camera, slit, noise.

    Args:
        sample: a stored sample (record fields suffice).
        shape: the sample's shape, if already made (it is regenerated from the identity otherwise).

    Returns:
        A :class:`pssnet_core.data.scenes.RenderedView`; its depth equals the stored crop inside the crop.
    """
    shape = shape if shape is not None else shape_of(sample["identity"])
    slit_columns = sample.get("slit_columns")
    view = ObjectScene(shape).render(
        np.asarray(sample["object_pose"]), np.asarray(sample["camera_pose"]), sample_intrinsics(sample),
        noise=SensorNoise(**sample["noise"]) if sample.get("noise") else None,
        noise_seed=int(sample.get("noise_seed", 0)))
    if slit_columns is not None:
        outside = np.ones(view.depth.shape[1], dtype=bool)
        outside[slit_columns[0]:slit_columns[1]] = False
        view.depth[:, outside] = 0.0
        view.mask[:, outside] = 0
        view.slit_columns = (int(slit_columns[0]), int(slit_columns[1]))
    return view


__all__ = [
    "CROP_MARGIN_PX", "DATASET_NAMES", "DEFAULT_OBJECTS", "FAMILY_CHOICES", "SCALES", "DatasetSpec", "DatasetSpecError",
    "MUG_VIEWS", "NARROW_SLIT_M", "WIDE_SLIT_M", "YCB_ROTATIONS", "ViewPlan", "dataset_specs", "full_images",
    "make_sample", "plan_view", "rerender", "sample_intrinsics",
]
