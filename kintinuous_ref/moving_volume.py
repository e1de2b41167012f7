"""Kintinuous' moving volume (paper III, Fig. 2): the TSDF follows the camera as a cyclical
buffer, the surface that leaves it is extracted slice by slice, and the map grows without bound
while the memory stays that of one volume.

The grid. Every voxel of the world has a fixed integer GLOBAL index g (its centre at
anchor + voxel_size g, the anchor being the first volume's voxel (0, 0, 0)). The volume is a
window of N^3 consecutive global voxels starting at `corner`; its logical voxel l = g - corner is
stored in array cell (l + offset) mod N (tsdf.TsdfVolume). Shifting the window by s voxels along
an axis moves no data: corner and offset grow by s, and the s layers of cells that left the
window are extracted and cleared; the same cells then hold the s layers that entered on the other
side.

When to shift (docs/parameters.md). The followed point is where the volume's centre was, in the
first camera's frame: the camera centre itself with placement "centred" (Kintinuous), the point
size/2 along the optical axis with "ahead" (so a camera that turns drags the volume to where it
looks). It starts at the volume centre, the "basis". When it is >= shift_threshold voxels from the
basis on any axis, the window shifts by the rounded displacement on every axis, each clamped to
shift_threshold voxels; the basis is again the window's centre.

Extraction by marching cubes (the paper triangulates extracted points by greedy projection;
docs/parameters.md: marching cubes on the slice's TSDF instead). A cube of 2x2x2 voxels is named by
its lower corner. When layers leave, every cube that holds a leaving voxel and lies in the window is
triangulated now: the leaving slab PLUS the first staying layer (the cubes straddling the boundary).
Those cubes can never be generated again (one of their voxels is no longer in the window), and every
later cube lies wholly in the window, so each cube is triangulated exactly once and neighbouring
slices share the vertices on their common faces. A vertex lies on a grid edge; its KEY is the edge
(global index of its lower voxel + axis), so the final mesh merges seam vertices exactly by key. A
vertex is kept when both voxels of its edge have weight >= min_extract_weight (8:
docs/parameters.md; fewer while fewer frames have been fused), a triangle when its three vertices
are kept.

Slices go to disk as they are made (slice_000000.ply, ...: binary PLY with colours and keys,
written to a temporary name and renamed, so a crash leaves only complete files). At the end the
rest of the window is extracted as the last slice and the slices are merged, streaming, into one
mesh.ply. One caveat: a straddling cube is triangulated with the staying layer's values at the
time it left; if later fusion flips the sign of one of those voxels, the next slice's surface
meets the seam at a different edge (a crack one voxel long). With a static scene and weights
>= 8 this does not occur in practice (tests/test_moving_volume.py counts the open edges).
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.errors import DatasetError
from kintinuous_ref.mesh import Mesh
from kintinuous_ref.tsdf import TsdfVolume

SLICE_NAME = "slice_{:06d}.ply"
_SLICE_FILE = re.compile(r"slice_(\d{6})\.ply$")
ON_VOXEL = 3  # key axis of a vertex that sits exactly on a voxel (TSDF exactly 0 there)
_ON_EDGE = 1e-3  # voxels: a vertex coordinate closer than this to an integer lies on it
_KEY_BITS = 20  # per axis in the int64 merge code: +-524 288 voxels (8 km at 1.6 cm voxels)


@dataclass
class SliceMesh(Mesh):
    """A Mesh whose vertices also carry their grid-edge keys, and the global voxel box
    [box_lo, box_hi) of the voxels whose cubes it triangulated."""

    keys: np.ndarray | None = None  # (V, 4) int32: edge's lower global voxel (3), axis 0..3
    box_lo: np.ndarray | None = None  # (3,) int64
    box_hi: np.ndarray | None = None  # (3,) int64

    def seam(self) -> np.ndarray:
        """True for the vertices that another slice may share: those on the border of this
        slice's mesh (an edge used by one triangle only). A vertex inside the mesh has its whole
        fan of triangles here, so no other slice's triangle can use it; a vertex on the seam has
        the rest of its fan in the neighbouring slice. (Faces of the slice's box would not do:
        a window that moves back re-enters space whose surface was already extracted.)"""
        edges = np.sort(self.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        code = edges[:, 0] * len(self.points) + edges[:, 1]
        unique, counts = np.unique(code, return_counts=True)
        border = unique[counts == 1]
        on_border = np.zeros(len(self.points), dtype=bool)
        on_border[border // len(self.points)] = True
        on_border[border % len(self.points)] = True
        return on_border


def merge_codes(keys: np.ndarray) -> np.ndarray:
    """One int64 per key (V, 4): the edge's global voxel (biased to be >= 0) and axis."""
    bias = 1 << (_KEY_BITS - 1)
    code = np.zeros(len(keys), dtype=np.int64)
    for axis in range(3):
        code = (code << _KEY_BITS) | (keys[:, axis].astype(np.int64) + bias)
    return (code << 2) | np.minimum(keys[:, 3], 3).astype(np.int64)


# ----------------------------------------------------------------------------------------------
# When and how far to shift


def followed_point(volume: TsdfVolume, first_pose: np.ndarray) -> np.ndarray:
    """The volume centre in the first camera's frame: the point the volume keeps near its centre
    (module docstring)."""
    return se3.transform_points(se3.inverse(first_pose), volume_centre(volume)[None])[0]


def volume_centre(volume: TsdfVolume) -> np.ndarray:
    """World position of the window's centre, the shift basis."""
    return volume.origin + 0.5 * (volume.resolution - 1) * volume.voxel_size


def shift_for(
    volume: TsdfVolume, pose: np.ndarray, follow: np.ndarray, threshold: int
) -> np.ndarray:
    """Voxels (3,) int to shift the window by for the camera at `pose`: zero unless the followed
    point is >= threshold voxels from the basis on some axis; then the rounded displacement on
    every axis, each clamped to +-threshold (docs/parameters.md)."""
    point = pose[:3, :3] @ follow + pose[:3, 3]
    displacement = (point - volume_centre(volume)) / volume.voxel_size
    if np.all(np.abs(displacement) < threshold):
        return np.zeros(3, dtype=np.int64)
    return np.clip(np.rint(displacement), -threshold, threshold).astype(np.int64)


# ----------------------------------------------------------------------------------------------
# Extraction


def extract_box(
    volume: TsdfVolume,
    lo: tuple[int, int, int],
    hi: tuple[int, int, int],
    corner: np.ndarray,
    min_weight: float,
) -> SliceMesh:
    """Marching cubes over the logical voxel box [lo, hi) of the window whose logical voxel 0 is
    global voxel `corner`: every cube with all 8 voxels in the box, triangulated once, with keys.
    """
    import pyvista

    lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
    box_lo, box_hi = corner + lo, corner + hi
    cells = volume.cells(tuple(lo), tuple(hi))
    weight = volume.weight[cells]
    shape = weight.shape
    if min(shape) < 2 or not (weight >= min_weight).any():
        return _empty_slice(box_lo, box_hi)
    tsdf = volume.tsdf[cells]
    # The box in its own index units (origin 0, spacing 1): VTK's float32 vertex coordinates then
    # stay small and exact enough to name their edge (world coordinates could be kilometres).
    grid = pyvista.ImageData(dimensions=shape, spacing=(1, 1, 1), origin=(0, 0, 0))
    grid.point_data["tsdf"] = tsdf.ravel(order="F")  # VTK: x fastest
    surface = grid.contour([0.0], scalars="tsdf", method="flying_edges", compute_normals=False)
    if surface.n_points == 0:
        return _empty_slice(box_lo, box_hi)
    local = np.asarray(surface.points, dtype=np.float64)
    triangles = surface.faces.reshape(-1, 4)[:, 1:].astype(np.int64)

    # Which grid edge each vertex lies on: two coordinates are whole numbers, the third is not
    # (or none is: the vertex sits on a voxel).
    distance = np.abs(local - np.rint(local))
    axis = np.argmax(distance, axis=1)
    axis[distance.max(axis=1) < _ON_EDGE] = ON_VOXEL
    lower = np.rint(local).astype(np.int64)
    along = np.flatnonzero(axis < 3)
    lower[along, axis[along]] = np.floor(local[along, axis[along]]).astype(np.int64)
    lower = np.clip(lower, 0, np.array(shape) - 1)
    upper = lower.copy()
    upper[along, axis[along]] += 1
    upper = np.minimum(upper, np.array(shape) - 1)

    # Keep vertices whose edge's voxels are both confidently observed.
    w_lower = weight[lower[:, 0], lower[:, 1], lower[:, 2]]
    w_upper = weight[upper[:, 0], upper[:, 1], upper[:, 2]]
    keep = (w_lower >= min_weight) & (w_upper >= min_weight)
    triangles = triangles[keep[triangles].all(axis=1)]
    used = np.zeros(len(local), dtype=bool)
    used[triangles.ravel()] = True
    new_index = np.cumsum(used) - 1
    local, lower, upper, axis = local[used], lower[used], upper[used], axis[used]

    colours = _edge_colours(volume, cells, local, lower, upper, axis)
    keys = np.column_stack([box_lo + lower, axis]).astype(np.int32)
    points = volume.voxel_to_world(lo + local)
    return SliceMesh(
        points=points.astype(np.float32),
        triangles=new_index[triangles],
        colours=colours,
        keys=keys,
        box_lo=box_lo,
        box_hi=box_hi,
    )


def _edge_colours(
    volume: TsdfVolume,
    cells: tuple,
    local: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    axis: np.ndarray,
) -> np.ndarray:
    """RGB of vertices on grid edges: linear interpolation of the edge's two voxels over those
    that received colour (colour.surface_colour restricted to an edge); black if neither did."""
    colours = np.zeros((len(local), 3), dtype=np.uint8)
    if volume.colour is None or len(local) == 0:
        return colours
    rgb, weight = volume.colour[cells], volume.colour_weight[cells]
    t = np.zeros(len(local))
    along = np.flatnonzero(axis < 3)
    t[along] = local[along, axis[along]] - lower[along, axis[along]]
    total = np.zeros((len(local), 3))
    coverage = np.zeros(len(local))
    for end, w in ((lower, 1.0 - t), (upper, t)):
        i, j, k = end.T
        w = w * (weight[i, j, k] > 0)
        total += w[:, None] * rgb[i, j, k]
        coverage += w
    coloured = coverage > 1e-6
    colours[coloured] = np.clip(np.rint(total[coloured] / coverage[coloured, None]), 0, 255)
    return colours


def _empty_slice(box_lo: np.ndarray, box_hi: np.ndarray) -> SliceMesh:
    return SliceMesh(
        points=np.zeros((0, 3), np.float32),
        triangles=np.zeros((0, 3), np.int64),
        colours=np.zeros((0, 3), np.uint8),
        keys=np.zeros((0, 4), np.int32),
        box_lo=box_lo,
        box_hi=box_hi,
    )


def clear_box(volume: TsdfVolume, lo: tuple[int, int, int], hi: tuple[int, int, int]) -> None:
    """Forget the logical voxels [lo, hi): TSDF, weight, colour and colour weight to 0."""
    cells = volume.cells(lo, hi)
    volume.tsdf[cells] = 0.0
    volume.weight[cells] = 0.0
    if volume.colour is not None:
        volume.colour[cells] = 0.0
        volume.colour_weight[cells] = 0.0


# ----------------------------------------------------------------------------------------------
# Slices on disk (or in memory)

_SLICE_VERTEX = np.dtype(
    [
        ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
        ("red", "u1"), ("green", "u1"), ("blue", "u1"),
        ("gx", "<i4"), ("gy", "<i4"), ("gz", "<i4"), ("axis", "u1"),
    ]
)  # fmt: skip
_FACE = np.dtype([("n", "u1"), ("v", "<i4", (3,))])


def write_slice(path: Path, mesh: SliceMesh) -> None:
    """A slice as binary PLY: position, colour and edge key per vertex, triangles; the box in a
    comment. Written under a temporary name and renamed: a crash never leaves half a file."""
    vertex = np.zeros(len(mesh.points), dtype=_SLICE_VERTEX)
    for i, name in enumerate(("x", "y", "z")):
        vertex[name] = mesh.points[:, i]
    for i, name in enumerate(("red", "green", "blue")):
        vertex[name] = mesh.colours[:, i]
    for i, name in enumerate(("gx", "gy", "gz", "axis")):
        vertex[name] = mesh.keys[:, i]
    face = np.zeros(len(mesh.triangles), dtype=_FACE)
    face["n"], face["v"] = 3, mesh.triangles
    box = " ".join(str(int(v)) for v in (*mesh.box_lo, *mesh.box_hi))
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment kintinuous slice\n"
        f"comment box {box}\nelement vertex {len(vertex)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "property int gx\nproperty int gy\nproperty int gz\nproperty uchar axis\n"
        f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    path = Path(path)
    out = tempfile.NamedTemporaryFile("wb", dir=path.parent, suffix=".part", delete=False)
    try:
        with out:
            out.write(header.encode("ascii"))
            out.write(vertex.tobytes())
            out.write(face.tobytes())
        os.replace(out.name, path)
    except BaseException:  # a full disk, a signal: no .part file stays behind
        Path(out.name).unlink(missing_ok=True)
        raise


def _element_count(header: list[str], element: str) -> int:
    return int(next(line for line in header if line.startswith(f"element {element} ")).split()[2])


def read_slice(path: Path) -> SliceMesh:
    """A slice written by write_slice."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if end < 0 or not data.startswith(b"ply\n"):
        raise DatasetError(f"{path}: not a PLY slice written by kintinuous")
    header = data[:end].decode("ascii").splitlines()
    try:
        box = next(line for line in header if line.startswith("comment box ")).split()[2:]
        vertices, faces = _element_count(header, "vertex"), _element_count(header, "face")
    except (StopIteration, ValueError, IndexError):
        raise DatasetError(f"{path}: not a PLY slice written by kintinuous") from None
    start = end + len(b"end_header\n")
    vertex = np.frombuffer(data, dtype=_SLICE_VERTEX, count=vertices, offset=start)
    face = np.frombuffer(
        data, dtype=_FACE, count=faces, offset=start + vertices * _SLICE_VERTEX.itemsize
    )
    return SliceMesh(
        points=np.column_stack([vertex["x"], vertex["y"], vertex["z"]]),
        triangles=face["v"].astype(np.int64),
        colours=np.column_stack([vertex["red"], vertex["green"], vertex["blue"]]),
        keys=np.column_stack([vertex["gx"], vertex["gy"], vertex["gz"], vertex["axis"]]),
        box_lo=np.array(box[:3], dtype=np.int64),
        box_hi=np.array(box[3:], dtype=np.int64),
    )


class SliceStore:
    """Where extracted slices go: files slice_NNNNNN.ply in `folder` (written at once, so an
    interrupted or crashed run keeps them), or a list in memory when `folder` is None.
    `fresh` deletes slices an earlier run left in the folder; fresh=False opens them instead
    (e.g. to assemble the mesh of a run that crashed)."""

    def __init__(self, folder: Path | None = None, fresh: bool = True) -> None:
        self.folder = None if folder is None else Path(folder)
        self.count = 0
        self._memory: list[SliceMesh] = []
        if self.folder is not None:
            self.folder.mkdir(parents=True, exist_ok=True)
            for stale in self.paths():
                if fresh:
                    stale.unlink()
                else:
                    self.count = max(self.count, int(_SLICE_FILE.search(stale.name).group(1)) + 1)

    def add(self, mesh: SliceMesh) -> None:
        if self.folder is None:
            self._memory.append(mesh)
        else:
            write_slice(self.folder / SLICE_NAME.format(self.count), mesh)
        self.count += 1

    def paths(self) -> list[Path]:
        if self.folder is None:
            return []
        return sorted(p for p in self.folder.iterdir() if _SLICE_FILE.search(p.name))

    def __iter__(self) -> Iterator[SliceMesh]:
        if self.folder is None:
            yield from self._memory
        else:
            for path in self.paths():
                yield read_slice(path)

    def rewrite(self, change: Callable[[int, SliceMesh], SliceMesh]) -> None:
        """Replace every slice by `change(number, slice)`, one slice in memory at a time (loop
        closure moves the vertices of the map it deforms)."""
        if self.folder is None:
            self._memory = [change(number, mesh) for number, mesh in enumerate(self._memory)]
            return
        for path in self.paths():
            number = int(_SLICE_FILE.search(path.name).group(1))
            write_slice(path, change(number, read_slice(path)))


# ----------------------------------------------------------------------------------------------
# The moving volume


class MovingVolume:
    """The cyclical buffer's bookkeeping around a TsdfVolume: when to shift, the slices that
    leave, and the final extraction. The volume's origin stays the world position of its logical
    voxel (0, 0, 0), so integration, raycasting and poses all stay in world coordinates."""

    def __init__(
        self,
        volume: TsdfVolume,
        first_pose: np.ndarray,
        config: VolumeConfig,
        store: SliceStore | None = None,
    ) -> None:
        self.volume = volume
        self.threshold = config.shift_threshold
        self.min_weight = config.min_extract_weight
        self.store = store if store is not None else SliceStore()
        self.anchor = np.array(volume.origin, dtype=np.float64)  # world position of global 0
        self.corner = np.zeros(3, dtype=np.int64)  # global index of logical voxel 0
        self.follow = followed_point(volume, np.asarray(first_pose, dtype=np.float64))
        self.shifts = 0  # frames on which the window moved
        self.fused = 0  # frames fused so far (update() is called once before each)
        self.finished = False

    @property
    def extract_weight(self) -> float:
        """min_extract_weight, but never more than the frames fused so far: a run shorter than
        8 frames would otherwise extract nothing at all."""
        return float(min(self.min_weight, max(1, self.fused)))

    @property
    def slices(self) -> int:
        return self.store.count

    def update(self, pose: np.ndarray) -> np.ndarray:
        """Shift the window for the camera at `pose` if it moved far enough (module docstring);
        returns the shift in voxels (zero when none)."""
        shift = shift_for(self.volume, pose, self.follow, self.threshold)
        if shift.any():
            self.shifts += 1
            for axis in range(3):
                if shift[axis]:
                    self.shift_axis(axis, int(shift[axis]))
        self.fused += 1
        return shift

    def shift_axis(self, axis: int, voxels: int) -> None:
        """Move the window by `voxels` (0 < |voxels| <= N) along `axis`: extract the cubes that
        hold a leaving voxel (the leaving layers plus the first staying layer), clear the leaving
        layers, then move corner, offset and origin."""
        n = self.volume.resolution
        lo, hi = [0, 0, 0], [n, n, n]
        leave_lo, leave_hi = [0, 0, 0], [n, n, n]
        if voxels > 0:  # layers 0..voxels-1 leave; layer `voxels` stays (the overlap)
            leave_hi[axis] = voxels
            hi[axis] = min(voxels + 1, n)
        else:  # layers n+voxels..n-1 leave; layer n+voxels-1 stays
            leave_lo[axis] = n + voxels
            lo[axis] = max(n + voxels - 1, 0)
        mesh = extract_box(self.volume, tuple(lo), tuple(hi), self.corner, self.extract_weight)
        if len(mesh.triangles):
            self.store.add(mesh)
        clear_box(self.volume, tuple(leave_lo), tuple(leave_hi))
        self.corner[axis] += voxels
        self.volume.offset[axis] = (self.volume.offset[axis] + voxels) % n
        self.volume.origin = self.anchor + self.corner * self.volume.voxel_size

    def recentre(self, pose: np.ndarray) -> None:
        """Start afresh around the camera at `pose` (after a loop closure moved it): what the
        window holds becomes a slice (it was fused with the poses before the correction, and the
        map deformation moves it with them), the window is cleared and placed on the global grid
        so that the followed point of `pose` is at its centre."""
        n = self.volume.resolution
        mesh = extract_box(self.volume, (0, 0, 0), (n, n, n), self.corner, self.extract_weight)
        if len(mesh.triangles):
            self.store.add(mesh)
        clear_box(self.volume, (0, 0, 0), (n, n, n))
        point = pose[:3, :3] @ self.follow + pose[:3, 3]
        shift = np.rint((point - volume_centre(self.volume)) / self.volume.voxel_size)
        shift = shift.astype(np.int64)
        self.corner += shift
        self.volume.offset[:] = (np.asarray(self.volume.offset) + shift) % n
        self.volume.origin = self.anchor + self.corner * self.volume.voxel_size
        self.shifts += 1

    def finish(self) -> None:
        """Extract what is left in the window as the last slice (once)."""
        if self.finished:
            return
        n = self.volume.resolution
        mesh = extract_box(self.volume, (0, 0, 0), (n, n, n), self.corner, self.extract_weight)
        if len(mesh.triangles):
            self.store.add(mesh)
        self.finished = True


# ----------------------------------------------------------------------------------------------
# One mesh from the slices


def assemble(slices: SliceStore, path: Path) -> tuple[int, int]:
    """Merge the slices into one binary PLY (mesh.write_ply's format), seam vertices that share a
    key becoming one vertex. Streams: two passes over the slices, holding one slice and the seam
    vertices' codes at a time. Returns (vertices, triangles)."""
    # Pass 1: the distinct seam codes, and the counts the PLY header needs.
    seam_codes, vertices, faces = [], 0, 0
    for mesh in slices:
        seam = mesh.seam()
        seam_codes.append(merge_codes(mesh.keys[seam]))
        vertices += int((~seam).sum())
        faces += int((~_degenerate(mesh)).sum())
    unique = np.unique(np.concatenate(seam_codes)) if seam_codes else np.zeros(0, np.int64)
    vertices += len(unique)
    global_index = np.full(len(unique), -1, dtype=np.int64)  # set when first written

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    vertex_dtype = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")]
    )
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment kintinuous reconstruction\n"
        f"element vertex {vertices}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    # Pass 2: vertices straight into the PLY, faces into a side file appended at the end.
    written = 0
    with open(path, "wb") as out, tempfile.TemporaryFile(dir=path.parent) as face_file:
        out.write(header.encode("ascii"))
        for mesh in slices:
            seam = mesh.seam()
            seam_rows = np.flatnonzero(seam)
            position = np.searchsorted(unique, merge_codes(mesh.keys[seam_rows]))
            # A seam vertex is written by the first slice that has it (once, if a slice has it
            # twice); later ones point at it.
            _, first = np.unique(position, return_index=True)
            first_here = np.zeros(len(seam_rows), dtype=bool)
            first_here[first] = True
            write_seam = first_here & (global_index[position] < 0)
            write = ~seam
            write[seam_rows[write_seam]] = True
            rows = np.flatnonzero(write)
            index = np.full(len(mesh.points), -1, dtype=np.int64)
            index[rows] = written + np.arange(len(rows))
            global_index[position[write_seam]] = index[seam_rows[write_seam]]
            index[seam_rows] = global_index[position]
            record = np.zeros(len(rows), dtype=vertex_dtype)
            for i, name in enumerate("xyz"):
                record[name] = mesh.points[rows, i]
            for i, name in enumerate("rgb"):
                record[name] = mesh.colours[rows, i]
            out.write(record.tobytes())
            written += len(rows)
            triangles = index[mesh.triangles[~_degenerate(mesh)]]
            face = np.zeros(len(triangles), dtype=_FACE)
            face["n"], face["v"] = 3, triangles
            face_file.write(face.tobytes())
        face_file.seek(0)
        while chunk := face_file.read(1 << 24):
            out.write(chunk)
    assert written == vertices, (written, vertices)
    return vertices, faces


def _degenerate(mesh: SliceMesh) -> np.ndarray:
    """Triangles two of whose corners share a key (they collapse once keys are merged)."""
    code = merge_codes(mesh.keys)[mesh.triangles]
    return (code[:, 0] == code[:, 1]) | (code[:, 1] == code[:, 2]) | (code[:, 0] == code[:, 2])


def read_mesh(path: Path) -> Mesh:
    """A PLY written by mesh.write_ply or assemble (float xyz, uchar rgb, triangles)."""
    data = np.memmap(path, dtype=np.uint8, mode="r")
    end = bytes(data[: 1 << 16]).find(b"end_header\n")
    header = bytes(data[:end]).decode("ascii", "replace").splitlines()
    try:
        vertices, faces = _element_count(header, "vertex"), _element_count(header, "face")
    except (StopIteration, ValueError, IndexError):
        raise DatasetError(f"{path}: not a PLY mesh written by kintinuous") from None
    vertex_dtype = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")]
    )
    start = end + len(b"end_header\n")
    vertex = np.frombuffer(data, dtype=vertex_dtype, count=vertices, offset=start)
    face = np.frombuffer(
        data, dtype=_FACE, count=faces, offset=start + vertices * vertex_dtype.itemsize
    )
    return Mesh(
        points=np.column_stack([vertex["x"], vertex["y"], vertex["z"]]),
        triangles=face["v"].astype(np.int64),
        colours=np.column_stack([vertex["r"], vertex["g"], vertex["b"]]),
    )


def preview_mesh(
    slices: SliceStore, voxel_size: float, max_triangles: int, triangles_in_slices: int
) -> Mesh:
    """The slices' surface with about `max_triangles` triangles at most, for a picture: memory
    stays bounded however long the run (the full mesh is mesh.ply).

    Vertex clustering (Rossignac and Borrel 1993): the vertices in one cell of a world-anchored
    grid become one vertex at the cell's centre with their mean colour; triangles whose corners
    fall into fewer than three cells vanish. A marching-cubes mesh has about two triangles per
    voxel face it crosses, so cells s voxels wide keep about 1/s^2 of them. Each slice is
    clustered on its own, but the grid is shared, so neighbouring slices meet at the same
    cell centres (seam vertices are duplicated, which a picture does not show).
    """
    cell = voxel_size * max(1.0, np.sqrt(triangles_in_slices / max(max_triangles, 1)))
    points, colours, triangles, count = [], [], [], 0
    for mesh in slices:
        clustered = mesh if cell == voxel_size else _cluster(mesh, cell)  # as is under budget
        points.append(clustered.points)
        colours.append(clustered.colours)
        triangles.append(clustered.triangles + count)
        count += len(clustered.points)
    if not points:
        return _empty_slice(np.zeros(3, np.int64), np.zeros(3, np.int64))
    return Mesh(np.concatenate(points), np.concatenate(triangles), np.concatenate(colours))


def _cluster(mesh: Mesh, cell: float) -> Mesh:
    """One vertex per occupied grid cell (its centre, mean colour); distinct non-degenerate
    triangles between cells."""
    cells = np.floor(mesh.points / cell).astype(np.int64)
    occupied, vertex_cell = np.unique(cells, axis=0, return_inverse=True)
    vertex_cell = vertex_cell.reshape(-1)
    members = np.bincount(vertex_cell, minlength=len(occupied))[:, None]
    colour_sum = np.zeros((len(occupied), 3))
    np.add.at(colour_sum, vertex_cell, mesh.colours.astype(np.float64))
    corners = vertex_cell[mesh.triangles]
    distinct = (
        (corners[:, 0] != corners[:, 1])
        & (corners[:, 1] != corners[:, 2])
        & (corners[:, 0] != corners[:, 2])
    )
    # Keep one triangle per set of three cells (whatever its corner order).
    corners = corners[distinct]
    _, first = np.unique(np.sort(corners, axis=1), axis=0, return_index=True)
    return Mesh(
        points=((occupied + 0.5) * cell).astype(np.float32),
        triangles=corners[np.sort(first)],
        colours=np.rint(colour_sum / members).astype(np.uint8),
    )
