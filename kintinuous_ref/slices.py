"""The slices the moving volume extracts (paper III, Fig. 2; moving_volume.py makes them): their
mesh, whose vertices carry the grid-edge keys that join neighbouring slices, their files, and
the one mesh assembled from them at the end.

A vertex lies on a grid edge; its KEY is the edge (global index of its lower voxel + axis), so the
final mesh merges the vertices that neighbouring slices share on their seam exactly, by key.

Slices go to disk as they are made (slice_000000.ply, ...: binary PLY with colours and keys,
written to a temporary name and renamed, so a crash leaves only complete files). At the end the
rest of the window is extracted as the last slice and the slices are merged, streaming, into one
mesh.ply.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kintinuous_ref.errors import DatasetError
from kintinuous_ref.mesh import Mesh

SLICE_NAME = "slice_{:06d}.ply"
_SLICE_FILE = re.compile(r"slice_(\d{6})\.ply$")
ON_VOXEL = 3  # key axis of a vertex that sits exactly on a voxel (TSDF exactly 0 there)
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


def empty_slice(box_lo: np.ndarray, box_hi: np.ndarray) -> SliceMesh:
    """A slice without vertices, of the box [box_lo, box_hi)."""
    return SliceMesh(
        points=np.zeros((0, 3), np.float32),
        triangles=np.zeros((0, 3), np.int64),
        colours=np.zeros((0, 3), np.uint8),
        keys=np.zeros((0, 4), np.int32),
        box_lo=box_lo,
        box_hi=box_hi,
    )


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


def new_file_mode() -> int:
    """The mode `open()` gives a new file under this process's umask (0644 under the usual
    022), where a temporary file is created 0600."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


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
        os.chmod(out.name, new_file_mode())  # a temporary file is private; a result is not
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
        return empty_slice(np.zeros(3, np.int64), np.zeros(3, np.int64))
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
