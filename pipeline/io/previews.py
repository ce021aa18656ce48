"""Preview images (matplotlib, Agg): centre slices of every grid and a shaded surface rendering.

Each grid gets ``previews/slices_<name>.png``: three slices through the centre of the active bounding
box (normal to x, y and z), in world units, with isolines and the zero contour in black, the
way the papers draw fields. Signed fields use a diverging colour map centred at 0; component
labels a qualitative one (0 left white); Vec3S grids (colours) are drawn as RGB. The surface of
the solid is rendered shaded in ``previews/surface_mesh.png``.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from PIL import Image as PILImage

from pipeline.io.meshkernels import raster_surface, view_bounds
from pipeline.io.report import SURFACE_PNG
from pipeline.io.vdbgrids import min_max
from pipeline.io.vtkio import (
    SurfaceMesh,
    default_isovalue,
    extract_surface,
    is_vector,
    pick_surface_source,
    read_dense,
    triangle_indices,
    triangle_labels,
    union_active_bbox,
)
from pipeline.util.atomic import atomic_path

matplotlib.use("Agg")
with warnings.catch_warnings():  # a system matplotlib's mpl_toolkits may shadow Axes3D; not used here
    warnings.filterwarnings("ignore", message="Unable to import Axes3D")
    from matplotlib import colors as mcolors
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

AXES = "xyz"
MAX_PIXELS = 600  # longest side of a slice image before it is strided
VIEW_AZIM, VIEW_ELEV = -60.0, 25.0  # degrees, as matplotlib's 3D default view
RASTER_PIXELS = 1600  # surface picture rasterised at twice its size on screen, then downsampled


@dataclass
class Slice:
    """A 2D slab: values[h, v] with world coordinates of the horizontal/vertical axes."""

    values: np.ndarray
    h: np.ndarray
    v: np.ndarray
    axis: int
    position: float

    @property
    def labels(self) -> tuple[str, str]:
        h, v = (a for n, a in enumerate(AXES) if n != self.axis)
        return h, v

    @property
    def extent(self) -> list[float]:
        dh = (self.h[1] - self.h[0]) / 2 if len(self.h) > 1 else 0.5
        dv = (self.v[1] - self.v[0]) / 2 if len(self.v) > 1 else 0.5
        return [self.h[0] - dh, self.h[-1] + dh, self.v[0] - dv, self.v[-1] + dv]


def centre_slices(grid: Any, lo: np.ndarray, hi: np.ndarray, voxel_size: float) -> list[Slice]:
    """Slices through the box centre normal to x, y, z, read with ``copyToArray``."""
    centre = (lo + hi) // 2
    stride = max(1, int(np.ceil((hi - lo + 1).max() / MAX_PIXELS)))
    out = []
    for axis in range(3):
        start, shape = lo.copy(), hi - lo + 1
        start[axis], shape[axis] = centre[axis], 1
        plane = np.take(read_dense(grid, start, shape), 0, axis=axis)[::stride, ::stride]
        h_ax, v_ax = (a for a in range(3) if a != axis)
        h = (lo[h_ax] + stride * np.arange(plane.shape[0])) * voxel_size
        v = (lo[v_ax] + stride * np.arange(plane.shape[1])) * voxel_size
        out.append(Slice(plane, h, v, axis, float(centre[axis] * voxel_size)))
    return out


def value_range(grid: Any, slices: list[Slice]) -> tuple[float, float]:
    """Min/max of the grid's active values (the slices' values when nothing is active).

    Colour limits follow the active values, so a large background (e.g. far-field values of an
    HFRep grid) saturates instead of washing out the field.
    """
    if grid.activeVoxelCount() > 0:
        lo, hi = min_max(grid)
        return float(lo), float(hi)
    return min(float(s.values.min()) for s in slices), max(float(s.values.max()) for s in slices)


def _kind(name: str, grid: Any, vrange: tuple[float, float]) -> str:
    if is_vector(grid):
        return "rgb"
    if name == "component":
        return "labels"
    return "signed" if vrange[0] < 0.0 < vrange[1] else "sequential"


def _label_cmap(n: int) -> tuple[mcolors.Colormap, mcolors.Normalize]:
    base = matplotlib.colormaps["tab10" if n <= 10 else "tab20"]
    cmap = mcolors.ListedColormap([base(i % base.N) for i in range(max(n, 1))]).with_extremes(bad="white")
    return cmap, mcolors.BoundaryNorm(np.arange(0.5, max(n, 1) + 1.5), cmap.N)


def _norm_cmap(kind: str, vrange: tuple[float, float]) -> tuple[mcolors.Colormap | str, mcolors.Normalize]:
    lo, hi = vrange
    if kind == "labels":
        return _label_cmap(int(np.rint(hi)))
    if kind == "signed":  # each sign gets the full half of the map, so both sides stay readable
        return "RdBu_r", mcolors.TwoSlopeNorm(vcenter=0.0, vmin=lo, vmax=hi)
    return "viridis", mcolors.Normalize(lo, hi if hi > lo else lo + 1.0)


def isolevels(kind: str, lo: float, hi: float, per_side: int = 5) -> np.ndarray:
    """Isoline values: evenly spaced, for signed fields on each side of 0 (0 itself is drawn black)."""
    if kind == "signed":
        return np.concatenate([np.linspace(lo, 0.0, per_side + 1)[1:-1], np.linspace(0.0, hi, per_side + 1)[1:-1]])
    return np.linspace(lo, hi, 2 * per_side + 1)[1:-1]


def _draw_contours(ax: Any, sl: Slice, kind: str, norm: mcolors.Normalize, ref: Slice | None,
                   ref_iso: float) -> list[Any]:
    """Grey isolines of the field, its zero contour black; else the reference surface in black.
    Returns the contour sets drawn."""
    H, V = np.meshgrid(sl.h, sl.v, indexing="ij")
    drawn = []
    if kind in ("signed", "sequential") and min(sl.values.shape) > 1:
        levels = isolevels(kind, norm.vmin, norm.vmax)
        # only the levels the slice crosses (matplotlib warns on a slice that crosses none)
        levels = levels[(levels > np.nanmin(sl.values)) & (levels < np.nanmax(sl.values))]
        if len(levels):
            drawn.append(ax.contour(H, V, sl.values, levels=levels, colors="0.35", linewidths=0.5, alpha=0.7))
    if kind == "signed" and sl.values.min() < 0 < sl.values.max():
        drawn.append(ax.contour(H, V, sl.values, levels=[0.0], colors="black", linewidths=1.6))
    elif ref is not None and ref.values.min() < ref_iso < ref.values.max():
        colour = "white" if kind == "rgb" else "black"  # RGB slices are black where no colour is set
        drawn.append(ax.contour(H, V, ref.values, levels=[ref_iso], colors=colour, linewidths=1.2))
    return drawn


def _draw_slice(ax: Any, sl: Slice, kind: str, cmap: Any, norm: mcolors.Normalize) -> Any:
    if kind == "rgb":
        rgb = np.clip(np.transpose(sl.values, (1, 0, 2)), 0.0, 1.0)
        return ax.imshow(rgb, origin="lower", extent=sl.extent, interpolation="nearest")
    data = sl.values.T
    if kind == "labels":
        data = np.ma.masked_less_equal(np.rint(data), 0)
    return ax.imshow(data, origin="lower", extent=sl.extent, cmap=cmap, norm=norm,
                     interpolation="nearest" if kind == "labels" else "bilinear")


def _save(fig: Figure, path: Path, dpi: int) -> None:
    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", facecolor="white", pil_kwargs={"compress_level": PNG_LEVEL})


PNG_LEVEL = 3  # zlib level of the PNGs: 6 (PIL's default) took 0.33 s of a small run's 2.4 s of previews
_SLICE_GRID = {"left": 0.055, "right": 0.91, "bottom": 0.1, "top": 0.85, "wspace": 0.26}
_SLICE_BAR = (0.935, 0.12, 0.011, 0.7)  # colour bar axes (figure fractions)


class SliceSheet:
    """The slice figure of a run: three panels over one box (every grid is sliced through the
    centre of the union of the active boxes, so the axes, ticks, labels and titles are the same
    for every grid). Those fixed parts are drawn once; each grid then draws only its images,
    contours, colour bar and title over a copy of them (matplotlib's blitting). Making and
    drawing the axes and their tick labels again for every grid was most of the previews' cost:
    about 0.3 s per grid, ~2 s of a small run's 4.4 s."""

    def __init__(self, slices: list[Slice], dpi: int):
        # a fixed layout: constrained layout measured every tick label twice
        self.fig = Figure(figsize=(15, 5.2), dpi=dpi)
        self.axes = self.fig.subplots(1, 3, gridspec_kw=_SLICE_GRID)
        for ax, sl in zip(self.axes, slices, strict=True):
            e = sl.extent
            ax.set_xlim(e[0], e[1])
            ax.set_ylim(e[2], e[3])
            h, v = sl.labels
            ax.set_xlabel(f"{h} (world units)")
            ax.set_ylabel(f"{v} (world units)")
            ax.set_title(f"{AXES[sl.axis]} = {sl.position:.4g}", y=1.01)  # a fixed y: no tick-label bbox pass
            ax.set_aspect("equal")
        self.title = self.fig.suptitle(" ")
        self.canvas = FigureCanvasAgg(self.fig)
        spines = [sp for ax in self.axes for sp in ax.spines.values()]
        for sp in spines:  # drawn per grid, over its images, as a full draw orders them
            sp.set_visible(False)
        self.canvas.draw()
        self.background = self.canvas.copy_from_bbox(self.fig.bbox)
        for sp in spines:
            sp.set_visible(True)
        self.cax = None  # made after the background is taken: it is drawn per grid
        self._drawn: list[Any] = []

    def draw(self, name: str, grid: Any, slices: list[Slice], ref: list[Slice] | None, ref_iso: float) -> None:
        """The picture of one grid: three slice panels with a shared colour bar."""
        vrange = (0.0, 1.0) if is_vector(grid) else value_range(grid, slices)
        kind = _kind(name, grid, vrange)
        cmap, norm = _norm_cmap(kind, vrange) if kind != "rgb" else (None, mcolors.Normalize())
        self.canvas.restore_region(self.background)
        drawn, image = [], None
        for n, (ax, sl) in enumerate(zip(self.axes, slices, strict=True)):
            image = _draw_slice(ax, sl, kind, cmap, norm)
            contours = _draw_contours(ax, sl, kind, norm, ref[n] if ref else None, ref_iso)
            mine = [image, *(a for cs in contours for a in _contour_artists(cs))]
            for artist in (*mine, *ax.spines.values()):
                ax.draw_artist(artist)
            drawn += mine
        if kind != "rgb":
            # one colour bar axes, cleared per grid: removing a colour bar puts its image's axes
            # back at their position before the aspect was applied
            if self.cax is None:
                self.cax = self.fig.add_axes(_SLICE_BAR)
            else:
                self.cax.clear()
            bar = self.fig.colorbar(image, cax=self.cax, label=_bar_label(name, kind))
            if kind == "labels" and norm.vmax <= 21:
                bar.set_ticks(np.arange(1, int(norm.vmax - 0.5) + 1))
            self.fig.draw_artist(self.cax)
        line = "white" if kind == "rgb" else "black"
        self.title.set_text(f"{name}  ({grid.gridClass}, {grid.valueTypeName}): centre slices, "
                            f"{line} = zero level / surface")
        self.fig.draw_artist(self.title)
        self._drawn = drawn

    def rgb(self) -> np.ndarray:
        """The picture drawn last, (height, width, 3) uint8."""
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def clear(self) -> None:
        """Remove the last grid's artists (the colour bar axes is cleared by the next grid)."""
        for artist in self._drawn:
            artist.remove()
        self._drawn = []

    def save(self, path: Path) -> None:
        """The picture drawn last as a PNG, then :meth:`clear`."""
        with atomic_path(path) as tmp:
            PILImage.fromarray(self.rgb()).save(tmp, format="png", compress_level=PNG_LEVEL)
        self.clear()


def _contour_artists(cs: Any) -> list[Any]:
    """The artists of a contour set: the set itself (matplotlib >= 3.8, an Artist), or its line
    collections (3.6 and 3.7, Debian's python3-matplotlib)."""
    return [cs] if hasattr(cs, "draw") else list(cs.collections)


def _bar_label(name: str, kind: str) -> str:
    return {"labels": f"{name} label", "signed": f"{name} (diverging, centred at 0)"}.get(kind, name)


def write_slice_previews(out_dir: str | os.PathLike, grids: Mapping[str, Any], voxel_size: float,
                         dpi: int = 100) -> list[Path]:
    """``<out_dir>/slices_<name>.png`` for every grid; returns the paths written."""
    box = union_active_bbox(grids.values())
    if box is None:
        return []
    lo, hi = box
    ref_name = _reference(grids)
    ref = centre_slices(grids[ref_name], lo, hi, voxel_size) if ref_name else None
    ref_iso = default_isovalue(ref_name, grids[ref_name]) if ref_name else 0.0
    paths = []
    sheet = None
    for name, grid in grids.items():
        slices = centre_slices(grid, lo, hi, voxel_size)
        sheet = sheet or SliceSheet(slices, dpi)
        sheet.draw(name, grid, slices, ref, ref_iso)
        path = Path(out_dir) / f"slices_{safe_name(name)}.png"
        sheet.save(path)
        paths.append(path)
    return paths


def safe_name(name: str) -> str:
    """A grid name usable as part of a file name (anything but letters, digits, ._- becomes _)."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", name) or "grid"


def _reference(grids: Mapping[str, Any]) -> str | None:
    try:
        return pick_surface_source(grids)
    except ValueError:
        return None


# --- surface rendering ------------------------------------------------------------------------
@dataclass
class View:
    """Orthographic camera: screen axes ``right``/``up``, ``eye`` points from the scene to the viewer."""

    right: np.ndarray
    up: np.ndarray
    eye: np.ndarray

    @classmethod
    def from_angles(cls, azim: float = VIEW_AZIM, elev: float = VIEW_ELEV) -> View:
        a, e = np.radians(azim), np.radians(elev)
        eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        right = np.array([-np.sin(a), np.cos(a), 0.0])
        return cls(right, np.cross(eye, right), eye)

    def project(self, p: np.ndarray) -> np.ndarray:
        return np.stack([p @ self.right, p @ self.up], axis=-1)

    @property
    def light(self) -> np.ndarray:
        v = 0.5 * self.right + 0.6 * self.up + self.eye
        return v / np.linalg.norm(v)


def _draw_frame(ax: Any, lo: np.ndarray, hi: np.ndarray, view: View) -> None:
    """The bounding box as a wireframe, its corner coordinates, and an x/y/z axis triad."""
    corners = np.array([[hi[0] if i else lo[0], hi[1] if j else lo[1], hi[2] if k else lo[2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    xy = view.project(corners)
    ax.add_collection(LineCollection([xy[[a, b]] for a, b in edges], colors="0.6", linewidths=0.6,
                                     zorder=0))
    for idx in (0, 7):
        c = corners[idx]
        ax.annotate(f"({c[0]:.3g}, {c[1]:.3g}, {c[2]:.3g})", xy[idx], fontsize=8, color="0.3",
                    ha="right" if idx == 0 else "left")
    size = 0.12 * float(np.max(hi - lo))
    origin = xy.min(axis=0) - 0.05 * size
    for axis, colour in zip(AXES, ("tab:red", "tab:green", "tab:blue"), strict=True):
        d = view.project(np.eye(3)[AXES.index(axis)]) * size
        ax.annotate("", origin + d, origin, arrowprops={"arrowstyle": "->", "color": colour, "lw": 1.5})
        ax.text(*(origin + 1.15 * d), axis, color=colour, fontsize=10, fontweight="bold")


def render_surface(path: str | os.PathLike, mesh: SurfaceMesh, component: Any | None = None,
                   voxel_size: float | None = None, raster: int = RASTER_PIXELS, dpi: int = 100,
                   view: View | None = None) -> Path:
    """Shaded orthographic rendering of ``mesh`` (coloured by label when ``component`` is given).

    Every triangle of the mesh is drawn by a compiled z-buffer rasteriser
    (pipeline.io.meshkernels.raster_surface: flat shading, ``raster`` pixels along the longer side of
    the picture, then shown with matplotlib's antialiased downsampling), under the bounding box and
    an axis triad from a fixed 3D view; this keeps it independent of mpl_toolkits, which a system
    matplotlib can shadow in a --system-site-packages environment. The labels are the mesh's own
    (extract_surface with a component grid), else sampled from ``component``.
    """
    view = view or View.from_angles()
    points, tris = mesh.points, mesh.triangles
    labels = None
    if component is not None and voxel_size and len(tris):
        labels = mesh.labels if mesh.labels is not None else triangle_labels(component, points, tris, voxel_size)
    if labels is None:
        palette = np.array([mcolors.to_rgb("#c9a66b")])
    else:
        cmap, _ = _label_cmap(int(max(labels.max(), 1)))
        palette = np.asarray(cmap(np.arange(cmap.N)))[:, :3]
    lo, hi = view_bounds(np.ascontiguousarray(points), view.right, view.up)
    lo2, hi2 = lo[3:], hi[3:]
    scale = raster / max(float((hi2 - lo2).max()), 1e-30)
    width, height = (int(np.ceil(float(e) * scale)) + 1 for e in hi2 - lo2)
    rgba = raster_surface(np.ascontiguousarray(points), triangle_indices(tris),
                          np.zeros(0, np.int32) if labels is None else np.ascontiguousarray(labels, dtype=np.int32),
                          np.ascontiguousarray(palette, dtype=np.float64), view.right, view.up, view.eye,
                          view.light, float(lo2[0]), float(lo2[1]), scale, width, height)
    fig = Figure(figsize=(8, 7), layout="constrained")
    ax = fig.add_subplot()
    ax.imshow(rgba, origin="lower", extent=(lo2[0], lo2[0] + width / scale, lo2[1], lo2[1] + height / scale),
              interpolation="antialiased", zorder=1)
    _draw_frame(ax, lo[:3], hi[:3], view)
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_axis_off()
    if labels is not None:
        ids = (np.flatnonzero(np.bincount(np.maximum(labels, 0))[1:]) + 1).tolist()  # np.unique: a sort
        cmap, _ = _label_cmap(max(ids, default=1))
        ax.legend(handles=[Patch(color=cmap((k - 1) % cmap.N), label=f"component {k}") for k in ids[:20]],
                  loc="upper right")
    ax.set_title(f"surface of '{mesh.source}' at {mesh.isovalue:g}: {len(mesh.triangles)} triangles")
    path = Path(path)
    _save(fig, path, dpi)
    return path


def write_previews(out_dir: str | os.PathLike, grids: Mapping[str, Any], voxel_size: float,
                   mesh: SurfaceMesh | None = None, dpi: int = 100) -> list[Path]:
    """All previews into ``out_dir`` (``<run>/previews``): slices_<grid>.png each, surface_mesh.png.

    ``mesh`` reuses the mesh already extracted for the .vtp; otherwise one is extracted here when a
    surface-like grid exists.
    """
    paths = write_slice_previews(out_dir, grids, voxel_size, dpi)
    if mesh is None and _reference(grids):
        mesh = extract_surface(grids, voxel_size)
    if mesh is not None and len(mesh.triangles):
        paths.append(render_surface(Path(out_dir) / SURFACE_PNG, mesh, grids.get("component"),
                                    voxel_size, dpi=dpi))
    return paths
