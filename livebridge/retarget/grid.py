"""A scanned face cropped and resampled onto a regular x-y grid (Erdoğdu §5.4): a quad mesh with UVs.

The face looks along +z (normalise it first, :mod:`livebridge.retarget.normalise`). Points are cropped to
a sphere around the nose tip, only the surface a frontal scanner sees is kept (points far behind the front
surface at the same x, y: the inside of a nostril or a mouth, the back of a head), and ``z`` is interpolated
linearly over the x-y Delaunay triangulation of the rest (``scipy.interpolate.griddata``) at ``150 x 150``
grid points. Grid points with no scan point within ``max_gap`` (holes, the eyes' openings, beyond the edge)
are masked, never invented: they are no vertex of the mesh (on a face scan's grid, only where they make a hole
the scan has, not a grid point that fell between its random points: :func:`_near_with_holes`). A coloured
scan's colours are interpolated the same way (the grid is then also an image of the skin).

The colours were also measured averaged by distance instead (normalised convolution: each point's colour
splatted bilinearly on the pixels, blurred by 0.2-0.7 of the points' spacing, divided by the splatted weight).
On a textured plane scanned twice at random (30k or 8k points over 76 mm, 0.5 mm pixels, patterns blurred by
0.4-1.5 mm, 0-0.2 mm of noise along the skin) the linear images lay closer to the pattern and to each other:
30k points, a 0.8 mm pattern, no noise along the skin, 0.024 RMS from the pattern and 0.022 between the two
scans against 0.040 and 0.052. An average of randomly placed points carries the pattern's change across its
window as noise; a linear interpolation only its curvature. The average was closer only for a pattern finer than
the pixels with 0.2 mm of noise along the skin (0.144 against 0.152 between the scans). In `livebridge bench
scans` it lowered the mean relative error by 1-5 % (60k points 0.0867 -> 0.0855, the other face 0.0889 ->
0.0844), no element crossing the bar and the right eyelid losing 0.011.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from livebridge.errors import InputError

GRID_SHAPE = (150, 150)
FRONT_DEPTH_MM = 10.0
"""Points more than this behind the front-most point of their grid cell are hidden from a frontal view."""
GAP_SPACINGS = 3.0
"""A grid point is a hole when no scan point is within this many median point spacings (or one cell)."""
HOLE_SEED_GAPS = 1.5
"""With seeded holes (:func:`resample`) a hole of the grid is where no scan point lies within this many gaps, grown
out to where one lies within the gap (:func:`_near_with_holes`): a grid point that only fell between the scan's
random points is none."""


@dataclass(frozen=True, eq=False)
class FaceGrid:
    """A height field ``z(x, y)`` on a regular grid, NaN where the scan has no surface.

    Attributes
    ----------
    x : ndarray, shape (n_cols,)
        Column coordinates, mm, increasing.
    y : ndarray, shape (n_rows,)
        Row coordinates, mm, increasing.
    heights : ndarray, shape (n_rows, n_cols)
        ``z`` at each grid point, NaN where masked.
    colours : ndarray, shape (n_rows, n_cols, 3), or None
        RGB in [0, 1] at each grid point (NaN where masked), None for a scan without colour.
    """

    x: np.ndarray
    y: np.ndarray
    heights: np.ndarray
    colours: np.ndarray | None = None

    def __post_init__(self):
        heights = np.array(self.heights, dtype=np.float64)
        if heights.shape != (len(self.y), len(self.x)):
            raise InputError(f"heights must have shape {(len(self.y), len(self.x))}, got {heights.shape}",
                             field="heights")
        quads = np.isfinite(heights)
        quads = quads[:-1, :-1] & quads[1:, :-1] & quads[:-1, 1:] & quads[1:, 1:]
        used = np.zeros(heights.shape, bool)  # a grid point in no complete quad is no vertex either
        for dr, dc in ((0, 0), (1, 0), (0, 1), (1, 1)):
            used[dr:dr + quads.shape[0], dc:dc + quads.shape[1]] |= quads
        heights[~used] = np.nan
        heights.setflags(write=False)
        object.__setattr__(self, "heights", heights)
        object.__setattr__(self, "_quads", quads)
        if self.colours is not None:
            colours = np.array(self.colours, dtype=np.float64).reshape(heights.shape + (3,))
            colours[~used] = np.nan
            colours.setflags(write=False)
            object.__setattr__(self, "colours", colours)

    @property
    def spacing(self) -> float:
        """The larger grid step of x and y, mm."""
        return float(max(np.diff(self.x).max(), np.diff(self.y).max()))

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape

    @property
    def valid(self) -> np.ndarray:
        """Grid points that are mesh vertices, shape (n_rows, n_cols)."""
        return np.isfinite(self.heights)

    @property
    def index(self) -> np.ndarray:
        """Vertex id of each grid point (row-major over valid points), -1 where masked; (n_rows, n_cols)."""
        out = np.full(self.shape, -1, dtype=np.int64)
        out[self.valid] = np.arange(int(self.valid.sum()))
        return out

    @property
    def vertices(self) -> np.ndarray:
        """The valid grid points, shape (n_vertices, 3), row-major."""
        xx, yy = np.meshgrid(self.x, self.y)
        valid = self.valid
        return np.stack([xx[valid], yy[valid], self.heights[valid]], axis=1)

    @property
    def uv(self) -> np.ndarray:
        """Texture coordinates of the vertices, shape (n_vertices, 2): column and row over the grid, in [0, 1]."""
        rows, cols = np.nonzero(self.valid)
        return np.stack([cols / max(self.shape[1] - 1, 1), rows / max(self.shape[0] - 1, 1)], axis=1)

    @property
    def quads(self) -> np.ndarray:
        """Quads with four valid corners, shape (n_quads, 4): vertex ids counter-clockwise seen from +z."""
        index = self.index
        rows, cols = np.nonzero(self._quads)
        return np.stack([index[rows, cols], index[rows, cols + 1], index[rows + 1, cols + 1], index[rows + 1, cols]],
                        axis=1)

    @property
    def triangles(self) -> np.ndarray:
        """Each quad split along its diagonal, shape (2 n_quads, 3), counter-clockwise seen from +z."""
        quads = self.quads
        return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])

    def write_obj(self, path: str | Path, vertices: np.ndarray | None = None) -> None:
        """The quad mesh with its UVs as an OBJ file (``v``, ``vt``, ``f v/vt``); at ``vertices`` (n_vertices, 3)
        when given (the grid's vertices moved: into a scan's coordinates); written whole or not at all."""
        from livebridge.atomic import write_bytes_atomically
        from livebridge.face.obj_file import mesh_obj

        vertices = self.vertices if vertices is None else vertices
        write_bytes_atomically(path, mesh_obj(vertices, self.quads, uv=self.uv), "grid OBJ file")


def square_axes(radius: float, shape: tuple[int, int] = GRID_SHAPE) -> tuple[np.ndarray, np.ndarray]:
    """(x (n_cols,), y (n_rows,)): ``shape`` grid lines over ``[-radius, radius]`` in x and y (mm)."""
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(f"the crop radius must be a positive number of mm, got {radius}", field="radius")
    rows, cols = shape
    if rows < 2 or cols < 2:
        raise InputError(f"a grid needs at least 2 x 2 points, got {rows} x {cols}", field="grid")
    return np.linspace(-radius, radius, cols), np.linspace(-radius, radius, rows)


def crop_sphere(points: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Mask, shape (n,), of points (n, 3) within ``radius`` of ``centre`` (3,)."""
    return np.linalg.norm(np.asarray(points) - np.asarray(centre), axis=1) <= radius


SPIKE_NEIGHBOURS = 16
"""The points in x-y a point's depth is judged against (:func:`spikes`)."""
SPIKE_MADS = 6.0
"""A flying point lies more than this many of its neighbours' median absolute distances from their plane ..."""
SPIKE_MIN_MM = 1.0
"""... and this much more (a scanner's noise alone is a few tenths of a mm)."""


def spikes(points: np.ndarray) -> np.ndarray:
    """Mask, shape (n,), of the flying points of a scan (n, 3; facing +z): a point further in depth from the
    plane through its :data:`SPIKE_NEIGHBOURS` nearest points in x-y than :data:`SPIKE_MADS` times their
    median absolute distance from it plus :data:`SPIKE_MIN_MM` (the plane fitted twice, the second time to
    the neighbours within 3 such distances of the first).

    Scanners leave stray points off the surface (a depth camera's flying pixels, a stereo mismatch). One in front
    of the face takes over its x-y cell: the resampling reads a cell's front-most points as the surface and cuts
    the skin behind it (:func:`front_surface`). In `livebridge bench scans`'s scans with 1 % of their points
    moved 2-20 mm along the view (either way), the jaw's element went 0.075 -> 0.162 relative RMS and the lip
    corner's surface 0.053 -> 0.121 (3 %: the brow's surface 0.030 -> 0.133). Stray points behind the face count
    too (cutting only those in front left the jaw at 0.179). A plane, not the neighbours' median depth, so that
    the face's steep sides (the jaw's line, the cheeks' outline) do not excuse a stray point in front of them
    (with the median depth, points 5-18 mm off stayed there and grid heights came out 11 mm off). Planes of
    x-y cells of 4-8 point spacings instead (0.4 s for 150k points instead of 3.5) missed a third to two thirds
    of the stray points: a face's cells on its steep sides hold a few points only. 2.4 s for 150k points (the
    resampling cuts a scan to its face first: 1.2 s for a textured mesh's samples).
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) <= SPIKE_NEIGHBOURS:
        return np.zeros(len(points), dtype=bool)
    _, near = cKDTree(points[:, :2]).query(points[:, :2], k=SPIKE_NEIGHBOURS + 1, workers=-1)
    near = near[:, 1:]
    # about the point itself, in float32: (n, k) arrays, which the time goes on
    dx, dy, depths = ((points[near, axis] - points[:, None, axis]).astype(np.float32) for axis in (0, 1, 2))
    weight = np.ones(near.shape, np.float32)
    for _ in range(2):
        sums = [np.sum(weight * term, axis=1) for term in (1.0, dx, dy, dx * dx, dx * dy, dy * dy)]
        normal = np.stack([np.stack(sums[0:3], -1), np.stack([sums[1], sums[3], sums[4]], -1),
                           np.stack([sums[2], sums[4], sums[5]], -1)], axis=1) + 1e-9 * np.eye(3)
        right = np.stack([np.sum(weight * depths * term, axis=1) for term in (1.0, dx, dy)], axis=1)
        plane = np.linalg.solve(normal.astype(np.float64), right[..., None].astype(np.float64))[..., 0]
        a, b, c = (plane[:, k:k + 1].astype(np.float32) for k in range(3))
        residual = np.abs(depths - a - b * dx - c * dy)
        spread = _median_of_kept(residual, weight > 0)
        weight = (residual <= 3.0 * spread[:, None] + 1e-6).astype(np.float32)
    return np.abs(plane[:, 0]) > SPIKE_MADS * spread + SPIKE_MIN_MM  # the point lies at depth 0 here


def _median_of_kept(values: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Per row of ``values`` (n, k), the median of its ``kept`` (n, k) bool entries (at least one a row)."""
    ordered = np.sort(np.where(kept, values, np.inf), axis=1)
    count = kept.sum(axis=1)
    rows = np.arange(len(values))
    return 0.5 * (ordered[rows, (count - 1) // 2] + ordered[rows, count // 2])


def front_surface(points: np.ndarray, cell: float, depth: float = FRONT_DEPTH_MM) -> np.ndarray:
    """Mask, shape (n,), of points (n, 3) within ``depth`` of the front-most (largest z) point of their
    x-y cell of size ``cell``: what a scanner looking along -z sees."""
    if not len(points):  # no point in the crop: the caller says so, naming the file
        return np.zeros(0, dtype=bool)
    which = cell_index(points[:, :2], cell)
    front = np.full(which.max() + 1, -np.inf)
    np.maximum.at(front, which, points[:, 2])
    return points[:, 2] >= front[which] - depth


def cell_index(points: np.ndarray, cell: float) -> np.ndarray:
    """Which cell of size ``cell`` each point (n, d) lies in, numbered 0 .. (cells occupied - 1), shape (n,).

    One integer key a cell, not ``np.unique(axis=0)`` of the cells' coordinates: that sorts rows as structured
    values, 2.7 s for 1.7M points in x-y (a dense scanner's face) against 0.4 s.
    """
    cells = np.floor(points / cell).astype(np.int64)
    cells -= cells.min(axis=0)
    key = np.zeros(len(cells), np.int64)
    for column, size in zip(cells.T, cells.max(axis=0) + 1):
        key = key * int(size) + column
    return np.unique(key, return_inverse=True)[1].ravel()


def holes(points: np.ndarray, x: np.ndarray, y: np.ndarray, max_gap: float) -> np.ndarray:
    """The grid points (n_rows, n_cols) bool with no point of the front surface of ``points`` (n, 3) within
    ``max_gap`` in x-y (the mask :func:`resample` leaves NaN, here for any gap)."""
    points = np.asarray(points, dtype=np.float64)
    points = points[front_surface(points, _cell(x, y))]
    return ~_near(points[:, :2], _grid_xy(x, y), max_gap).reshape(len(y), len(x))


def _cell(x: np.ndarray, y: np.ndarray) -> float:
    """The grid's largest step along either axis, mm."""
    return float(max(np.diff(x).max(), np.diff(y).max()))


def _grid_xy(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The grid's points (n_rows * n_cols, 2), row by row."""
    xx, yy = np.meshgrid(x, y)
    return np.stack([xx.ravel(), yy.ravel()], axis=1)


def _near(points_xy: np.ndarray, grid_xy: np.ndarray, max_gap: float) -> np.ndarray:
    """Which of ``grid_xy`` (m, 2) have a point of ``points_xy`` (n, 2) within ``max_gap``, shape (m,) bool."""
    gap, _ = cKDTree(points_xy).query(grid_xy, distance_upper_bound=max_gap, workers=-1)
    return np.isfinite(gap)


def _near_with_holes(points_xy: np.ndarray, grid_xy: np.ndarray, max_gap: float, shape: tuple[int, int]
                     ) -> np.ndarray:
    """``grid_xy`` (m, 2; rows of a ``shape`` grid) that are not in a hole of ``points_xy`` (n, 2), shape (m,)
    bool: a hole is a connected run of grid points with no point within ``max_gap`` that holds one with none
    within :data:`HOLE_SEED_GAPS` times it.

    A scanner's points are random, and their density changes over the face: with the gap alone, the bench's
    neutral scan of 60k points (a gap of one 1.48 mm cell, 3.9 median point spacings) left 13 holes of 1-3 grid
    points in the forehead, cheeks and chin, 30k points 107 (holes in the face of the basis's mesh, four quads a
    point); with the seeds none and 3. The eyes' openings (53 and 55 grid points at 60k) and an opened mouth are
    as before; a hole narrower than about three gaps is filled as the grid's cells are (of the 16 expression
    scans', one: a nostril flared by the levator labii, 22 grid points). The elements built on the filled grids
    (the bench's draws at 60k: seeds 7, 8, the other face) have means of 0.0874 / 0.0885 / 0.0893 relative RMS
    against 0.0867 / 0.0886 / 0.0889: seed 7's right eyelid went 0.177 -> 0.190 (one of its holes, 3 points, lay
    just above that lid's crease, where the built lid now moves 0.5-0.8 mm otherwise), the other face's lip
    corner 0.126 -> 0.133, its left eyelid 0.191 -> 0.189."""
    from scipy.ndimage import label

    gap, _ = cKDTree(points_xy).query(grid_xy, distance_upper_bound=HOLE_SEED_GAPS * max_gap, workers=-1)
    far = (gap > max_gap).reshape(shape)
    labels, _ = label(far, structure=np.ones((3, 3), bool))
    seeded = np.unique(labels[~np.isfinite(gap).reshape(shape)])
    return ~np.isin(labels, seeded[seeded > 0]).ravel()


def point_spacing(points_xy: np.ndarray) -> float:
    """The median distance from each point (n, 2) to its nearest neighbour."""
    distance, _ = cKDTree(points_xy).query(points_xy, k=2, workers=-1)
    return float(np.median(distance[:, 1]))


def resample(points: np.ndarray, x: np.ndarray, y: np.ndarray, max_gap: float | None = None,
             source=None, colours: np.ndarray | None = None, seeded_holes: bool = False) -> FaceGrid:
    """The surface of ``points`` (n, 3), facing +z, as heights on the grid ``x`` (n_cols,) by ``y`` (n_rows,).

    Parameters
    ----------
    points : ndarray, shape (n, 3)
        Already cropped to the face, mm.
    x, y : ndarray
        Grid lines, increasing.
    max_gap : float, optional
        A grid point with no scan point within this x-y distance (mm) is masked. Default: the larger of
        :data:`GAP_SPACINGS` median point spacings and one grid cell.
    source : str or Path, optional
        Named in errors.
    colours : ndarray, shape (n, 3), optional
        The points' RGB: interpolated like ``z`` into :attr:`FaceGrid.colours`.
    seeded_holes : bool
        Mask a grid point only in a hole that somewhere has no point within :data:`HOLE_SEED_GAPS` times
        ``max_gap`` (:func:`_near_with_holes`): a face scan's grid, the mesh a basis is written on.
    """
    points = np.asarray(points, dtype=np.float64)
    cell = _cell(x, y)
    front = front_surface(points, cell)
    points = points[front]
    if len(points) < 3 or np.linalg.matrix_rank(points[:, :2] - points[0, :2]) < 2:
        raise InputError(f"{len(points)} points in the face crop, not enough for a surface (is the nose tip "
                         "landmark on the scan, and the crop radius right?)", source, "points")
    if max_gap is None:
        max_gap = max(GAP_SPACINGS * point_spacing(points[:, :2]), cell)
    grid_xy = _grid_xy(x, y)
    if seeded_holes:
        near = _near_with_holes(points[:, :2], grid_xy, max_gap, (len(y), len(x)))
    else:
        near = _near(points[:, :2], grid_xy, max_gap)
    values = points[:, 2:] if colours is None else np.hstack([points[:, 2:], np.asarray(colours)[front]])
    interpolated = np.full((len(grid_xy), values.shape[1]), np.nan)
    interpolated[near] = _linear(points[:, :2], values, grid_xy[near])
    rgb = None if colours is None else interpolated[:, 1:].reshape(len(y), len(x), 3)
    grid = FaceGrid(x, y, interpolated[:, 0].reshape(len(y), len(x)), rgb)
    if not grid.valid.any():  # every later step needs a surface; points in a cell or two (wrong units) give none
        raise InputError(f"{len(points)} points in the face crop make no surface on the {len(x)} x {len(y)} grid "
                         f"of {cell:.3g} mm cells (are the scan's units and the crop radius right?)", source, "points")
    return grid


def _linear(points_xy: np.ndarray, values: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """``values`` (n, k) of points (n, 2) interpolated linearly at queries (m, 2) over the Delaunay
    triangulation (what ``griddata(method="linear")`` computes, without its threaded slowness: see
    :func:`containing_triangles`), NaN outside the hull; shape (m, k).
    """
    triangulation, simplex = containing_triangles(points_xy, queries)
    inside = simplex >= 0
    transform = triangulation.transform[simplex[inside]]  # (k, 3, 2): inverse affine and offset
    partial = np.einsum("kij,kj->ki", transform[:, :2], queries[inside] - transform[:, 2])
    barycentric = np.hstack([partial, 1 - partial.sum(axis=1, keepdims=True)])
    out = np.full((len(queries), values.shape[1]), np.nan)
    out[inside] = np.einsum("ki,kij->kj", barycentric, values[triangulation.simplices[simplex[inside]]])
    return out


def containing_triangles(points_xy: np.ndarray, queries: np.ndarray):
    """The Delaunay triangulation of ``points_xy`` (n, 2) and the index of the triangle holding each query
    (m, 2), -1 outside the hull: what the linear interpolation of :func:`resample` blends at each query.

    The triangles' barycentric transforms, which ``find_simplex`` needs for every triangle, are computed here
    at once (:func:`barycentric_transforms`): scipy inverts each triangle's 2 x 2 matrix with its own LAPACK
    call, 1.3-1.8 s for the 350k triangles of a face sampled every 0.5 mm (0.1 s here), and threaded OpenBLAS
    made that 10-20 s on a busy 2-core machine.
    """
    triangulation = _delaunay(np.ascontiguousarray(points_xy, dtype=np.float64))
    if hasattr(triangulation, "_transform"):  # scipy's cache of .transform, read by find_simplex
        triangulation._transform = barycentric_transforms(triangulation.points, triangulation.simplices)
        return triangulation, triangulation.find_simplex(queries)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return triangulation, triangulation.find_simplex(queries)


_LAST_TRIANGULATION: list = []
"""(digest of the points, their triangulation): a neutral's front points are triangulated for its resampling
and again for its surface fit (:mod:`~livebridge.retarget.surface_fit`), 2.4 s each for a face sampled every
0.5 mm."""


def _delaunay(points_xy: np.ndarray):
    import hashlib

    from scipy.spatial import Delaunay

    digest = (points_xy.shape, hashlib.blake2b(points_xy.tobytes(), digest_size=16).digest())
    if _LAST_TRIANGULATION and _LAST_TRIANGULATION[0] == digest:
        return _LAST_TRIANGULATION[1]
    triangulation = Delaunay(points_xy)
    _LAST_TRIANGULATION[:] = [digest, triangulation]
    return triangulation


def barycentric_transforms(points_xy: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """What scipy's ``Delaunay.transform`` holds (n_triangles, 3, 2): per triangle the inverse of the 2 x 2
    matrix of its first two corners less its third, then that third corner; NaN for a degenerate triangle.

    ``points_xy`` (n, 2), ``triangles`` (n_triangles, 3) indices.
    """
    corners = points_xy[triangles]  # (t, 3, 2)
    last = corners[:, 2]
    a, b = corners[:, 0] - last, corners[:, 1] - last  # the matrix's columns
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = np.stack([np.stack([b[:, 1], -b[:, 0]], axis=1), np.stack([-a[:, 1], a[:, 0]], axis=1)], axis=1)
        inverse /= (a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1])[:, None, None]
        # scipy's test: the reciprocal condition number in the 1-norm under 1000 eps
        rcond = 1.0 / (np.maximum(np.abs(a).sum(axis=1), np.abs(b).sum(axis=1))
                       * np.abs(inverse).sum(axis=1).max(axis=1))
    transforms = np.concatenate([inverse, last[:, None, :]], axis=1)
    transforms[~(rcond >= 1000 * np.finfo(float).eps)] = np.nan
    return transforms
