"""hfrep: eikonal distance (FIM) -> ``surface`` level set, ``hfrep`` (hfrep eq. 21) and a
``density`` fog volume; field-quality numbers for the manifest; attribute grids
parameterised by distance (hfrep section 7, ``attributes:``).

Library calls: pipeline.distance.eikonal.solve_distance / surface_leaves, pipeline.distance.hfrep.hfrep_blocks,
pipeline.distance.quality, pipeline.distance.attributes; the grids are made by pipeline.io.vdbgrids.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, Field, field_validator, model_validator

from pipeline.distance import attributes as attr
from pipeline.distance.attributes import check_formula
from pipeline.distance.eikonal import solve_distance, surface_leaves
from pipeline.distance.hfim import fill_deep, hierarchical_distance, hierarchical_tiles, interior_tiles
from pipeline.distance.hfrep import density_leaves, hfrep_blocks
from pipeline.distance.quality import field_report
from pipeline.io import vdbgrids as vg
from pipeline.sparse.blockwrite import LeafSource
from pipeline.util.errors import InputError
from pipeline.voxel.voxelise import LEAF_PEAK_BYTES, WORK_BYTES, estimate_interior_voxels
from stages.base import BandEstimate, FrepBand, StageParams

REQUIRES = (FrepBand,)
RESERVED = ("frep", "surface", "hfrep", "density", "component")
AttrFormula = Annotated[str, AfterValidator(check_formula)]


class Attribute(StageParams):
    """One attribute ``F_A(d, p)`` (hfrep seed section 5.2): a float grid or an RGB Vec3S grid."""

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_.-]*$", description="grid name")
    formula: AttrFormula | None = Field(default=None, description="float attribute in x y z t d")
    rgb: tuple[AttrFormula, AttrFormula, AttrFormula] | None = Field(
        default=None, description="Vec3S attribute: three formulas in x y z t d")
    outside: Literal["inactive", "surface"] = Field(
        default="inactive", description="outside the object: no values, or the surface value (d = 0) out to the band")

    @model_validator(mode="after")
    def _one_kind(self):
        if (self.formula is None) == (self.rgb is None):
            raise ValueError("give exactly one of formula (a float grid) or rgb (three formulas, a Vec3S grid)")
        return self


class Params(StageParams):
    solver: Literal["fim", "hfim"] = Field(
        default="fim", description="'hfim': 'surface' covers the domain box, far space as coarse tiles (docs/hfim.md)")
    order: Literal[1, 2] = Field(default=2, description="upwind scheme: 1 first-order Godunov, 2 second order")
    smoothing: Literal["tricubic"] = "tricubic"
    step: Literal["sigmoid", "tanh", "rational"] = Field(default="sigmoid", description="C1 step of eq. 21")
    slope: float = Field(default=0.01, gt=0, description="slope of the step (eq. 23), FRep units")
    max_distance: float | Literal["domain"] | None = Field(
        default=None, description="how far outside to solve, world units; 'domain' = everywhere; default 10 voxels")
    density: bool = Field(default=True, description="also write a 'density' fog volume (0..1) for Blender")
    surface: Literal["band", "full"] = Field(
        default="band", description="'surface' level set: narrow band of the voxelise band, or every solved voxel")
    quality: bool = Field(default=True, description="field-quality report into the manifest")
    interior: Literal["coarse", "fine"] = Field(
        default="coarse", description="'coarse': deeper inside than max_distance (and the band) as leaf-sized "
        "tiles from an 8-voxel solve (docs/hfim.md); 'fine': the whole interior at full resolution "
        "(always with attributes, surface: full, max_distance: domain or solver: hfim)")
    attributes: list[Attribute] = Field(default_factory=list, description="attribute grids of d, x, y, z, t")

    @field_validator("attributes")
    @classmethod
    def _names(cls, v):
        names = [a.name for a in v]
        clash = sorted({n for n in names if n in RESERVED or names.count(n) > 1})
        if clash:
            raise ValueError(f"attribute names must be unique and differ from {', '.join(RESERVED)}: {clash}")
        return v

    @field_validator("max_distance")
    @classmethod
    def _positive(cls, v):
        if isinstance(v, float) and v <= 0:
            raise ValueError("must be > 0")
        return v


def run(ctx, p: Params) -> dict:
    dom, fb = ctx.job.domain, ctx.get(FrepBand)
    frep, h, band = fb.blocks, dom.voxel_size, float(fb.band)
    maxd = 10 * h if p.max_distance is None else p.max_distance
    # with bricks, the (fine) FIM runs per brick on the workers, continued across brick faces
    # voxelise's leaves hold values of the right sign in every voxel: no flood fill of the band
    solve_kw = {"brick": ctx.job.bricks, "map_fn": ctx.map, "signed_values": fb.signed}
    if p.solver == "hfim":  # fine solve out to max_distance (default 16 voxels), coarse cells beyond
        reach = 16.0 if p.max_distance in (None, "domain") else p.max_distance / h
        hres = hierarchical_distance(frep, (dom.index_min, dom.index_max), fb.inside_boxes,
                                     fine_distance_vox=reach, order=p.order, **solve_kw)
        res = hres.fine
    else:
        res = solve_distance(frep, maxd, (dom.index_min, dom.index_max), fb.inside_boxes, order=p.order,
                             inside_distance=_inside_distance(p, maxd, band * h), **solve_kw)
    meta = ctx.grid_metadata("hfrep", p)
    hf = hfrep_blocks(frep, res, p.step, p.slope)
    if p.quality:
        ctx.manifest.setdefault("quality", {}).update(field_report(frep, res, hf))
    stats = dict(res.stats)
    if p.attributes:
        stats["attributes"] = _attributes(ctx, p, res, hf, band, meta)
    tiles = _interior(res, dom, p.order, stats)
    if tiles is not None:  # deep inside the step is +1: hfrep = d, density = 1 (d is past the ramp)
        fill_deep(hf, res, tiles[2])  # the fine blocks' inside voxels beyond the fine solve's limit
    # build the grids one at a time and drop each working copy: at 1024^3 the interior
    # distance is hundreds of millions of voxels
    hgrid = vg.frep_grid_of_leaves(LeafSource.of(hf, consume=True), "hfrep")  # hf released as written
    hgrid.updateMetadata({**meta, "step": p.step, "slope": p.slope})
    del hf
    if tiles is not None:
        vg.fill_tiles(hgrid, tiles[0], tiles[1])
    if p.density:
        coarse = None if tiles is None else (tiles[0], np.clip(tiles[1] / (band * h), 0.0, 1.0))
        ctx.grids["density"] = vg.fog_grid(*density_leaves(res, band * h, coarse), "density")
        ctx.grids["density"].updateMetadata(meta)
    if p.solver == "hfim":
        fine, coarse_tiles = hierarchical_tiles(hres, background=band * h)  # SPEC: background = band * h
        surface = vg.tiled_grid(fine, coarse_tiles, "surface", level_set=True)
        stats["hfim"] = {k: v for k, v in hres.stats.items() if k != "fine"}
    else:
        surface = vg.level_set_grid(surface_leaves(res, band, full=p.surface == "full", consume=True),
                                    "surface")  # the last use of res
    surface.updateMetadata(meta)
    ctx.grids["surface"], ctx.grids["hfrep"] = surface, hgrid
    return stats


def grids(p: Params) -> list[str]:
    """In the order they are written: surface, hfrep, density, then the attributes."""
    return ["surface", "hfrep", *(["density"] if p.density else []), *(a.name for a in p.attributes)]


HFREP_BYTES_PER_VOXEL = 30  # measured peak of the hfrep stage per interior voxel (docs/performance.md)
# the same for the shell the coarse-interior solve works on: the demo at 1024^3 (session 8) adds
# 1.75 GiB over what voxelise leaves for ~306 M shell voxels as estimated below (~6 bytes);
# 10 keeps a margin (the old 30 refused the demo at 2048^3 with 37 GiB that needs ~12)
SHELL_BYTES_PER_VOXEL = 10
# per interior voxel and attribute component: its grid (~4.5 bytes) and a margin for the values being made
ATTRIBUTE_BYTES_PER_COMPONENT = 6
SHELL_BLOCKS_PER_LEAF = 5  # fine blocks of a coarse-interior hfrep solve per band leaf (4.4 measured, demo 512^3)


def estimate_bytes(job, p: Params, band: BandEstimate) -> tuple[float, str]:
    """The band plus the voxels solved at full resolution: the whole interior, or with the
    coarse interior (:func:`_inside_distance`) a shell of blocks around the band."""
    fine = _solves_interior(p)
    if fine:
        voxels = estimate_interior_voxels(job.model, job.domain, band.voxels, job.t)
    else:
        voxels = SHELL_BLOCKS_PER_LEAF * max(band.bytes - WORK_BYTES, 0.0) / LEAF_PEAK_BYTES * 512.0
    per = HFREP_BYTES_PER_VOXEL if fine else SHELL_BYTES_PER_VOXEL
    # each attribute's grid stays in memory until the export (and its float32 values while it
    # is made): the microstructure's two at 1024^3 peaked 11 % over the estimate without them
    per += ATTRIBUTE_BYTES_PER_COMPONENT * sum(1 if a.formula is not None else 3 for a in p.attributes)
    need = band.bytes + per * voxels
    what = "interior distance" if fine else "distance near the surface"
    return need, f"its narrow band and the {what} of the hfrep stage"


def _solves_interior(p: Params) -> bool:
    """Whether the stage solves the whole interior at full resolution (the hierarchical solver
    always does; so does the FIM for attributes, a full surface and distances to the domain)."""
    return (p.interior == "fine" or bool(p.attributes) or p.surface == "full"
            or p.max_distance == "domain" or p.solver == "hfim")


def _inside_distance(p: Params, maxd, band_world: float) -> float | None:
    """How deep the fine solve goes inside: max_distance (at least the band) with the coarse
    interior, None (all of it) where the whole interior is wanted at full resolution."""
    if _solves_interior(p):
        return None
    return max(float(maxd), band_world)


def _interior(res, dom, order: int, stats: dict):
    """(tile origins, distances, values of the deep voxels of ``res.deep_rows``) of the coarse
    interior (pipeline.distance.hfim.interior_tiles), or None."""
    if res.coarse_inside is None:
        return None

    origins, values, fill, st = interior_tiles(res, (dom.index_min, dom.index_max), order)
    stats["coarse_interior"] = st
    return origins, values, fill


def _attributes(ctx, p: Params, res, hf, band: float, meta: dict) -> dict:
    """Evaluate and store every attribute grid; a formula that is not finite is a config error."""

    out, covered = {}, {}
    for a_index, a in enumerate(p.attributes):
        srcs = [a.formula] if a.formula is not None else list(a.rgb)
        if a.outside not in covered:  # the same voxels for every attribute of one ``outside``
            covered[a.outside] = attr.attribute_voxels(res, hf, a.outside, band)
        vox = covered[a.outside]
        try:
            values = attr.evaluate_attribute([attr.AttributeFormula(s) for s in srcs], vox, ctx.job.t)
        except attr.NonFiniteAttribute as e:
            tail = ("formula",) if a.formula is not None else ("rgb", e.component)
            raise InputError(str(e), ("attributes", a_index) + tail) from None
        grid = vg.attribute_grid(a.name, values, vox.origins, vox.active, vox.voxel_size)
        grid.updateMetadata({**meta, "attribute": a.name, "attribute_formulas": " ; ".join(srcs),
                             "attribute_outside": a.outside})
        ctx.grids[a.name] = grid
        out[a.name] = {"type": grid.valueTypeName, "active_voxels": int(grid.activeVoxelCount())}
    return out
