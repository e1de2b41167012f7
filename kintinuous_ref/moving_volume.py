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
its lower corner (marching_cubes.py, our own: no VTK). When layers leave, every cube that holds a
leaving voxel and lies in the window is triangulated now: the leaving slab PLUS the first staying
layer (the cubes straddling the boundary). Those cubes can never be generated again (one of their
voxels is no longer in the window), and every later cube lies wholly in the window, so each cube is
triangulated exactly once and neighbouring slices share the vertices on their common faces. A vertex
lies on a grid edge; its KEY is the edge (global index of its lower voxel + axis), so the final mesh
merges seam vertices exactly by key. A vertex is kept when both voxels of its edge have weight >=
min_extract_weight (8: docs/parameters.md; fewer while fewer frames have been fused), a triangle
when its three vertices are kept. The box's surface is the backend's mesh stage's (`mesh_box`,
box_surface.py's rules): the cuda backend meshes the box where the volume lies, on the device, and
downloads only the surface; this module names its vertices by key and places them in the world.

The slices, their files and the one mesh they make at the end are slices.py's. One caveat: a
straddling cube is triangulated with the staying layer's values at the time it left; if later
fusion flips the sign of one of those voxels, the next slice's surface meets the seam at a
different edge (a crack one voxel long). With a static scene and weights >= 8 this does not occur
in practice (tests/test_moving_volume.py counts the open edges).

    moving_volume.py  when and how far to shift, extracting the cubes that leave, MovingVolume
    box_surface.py    the surface of a box of the volume by the slices' rules (the mesh stages')
    slices.py         the slices' mesh and keys, their files, the one mesh assembled from them
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from kintinuous_ref import marching_cubes, se3
from kintinuous_ref.box_surface import BoxSurface
from kintinuous_ref.config import VolumeConfig
from kintinuous_ref.slices import (
    ON_VOXEL,
    SLICE_NAME,
    SliceMesh,
    SliceStore,
    assemble,
    empty_slice,
    merge_codes,
    preview_mesh,
    read_mesh,
    read_slice,
    write_slice,
)
from kintinuous_ref.tsdf import TsdfVolume

# The slices' names, importable from here too (slices.py).
__all__ = [
    "ON_VOXEL",
    "SLICE_NAME",
    "BoxMesher",
    "MovingVolume",
    "SliceMesh",
    "SliceStore",
    "assemble",
    "clear_box",
    "extract_box",
    "followed_point",
    "merge_codes",
    "preview_mesh",
    "read_mesh",
    "read_slice",
    "shift_for",
    "volume_centre",
    "write_slice",
]

# A mesh stage's mesh_box: (volume, lo, hi, min_weight) -> the box's BoxSurface.
BoxMesher = Callable[[TsdfVolume, tuple, tuple, float], BoxSurface]


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
    mesh_box: BoxMesher = marching_cubes.mesh_box,
) -> SliceMesh:
    """The slice of the logical voxel box [lo, hi) of the window whose logical voxel 0 is global
    voxel `corner`: the box's surface by `mesh_box` (a backend's mesh stage's; box_surface.py:
    every cube with all 8 voxels in the box triangulated once, a vertex kept when both voxels of
    its edge have weight >= min_weight), its vertices in world coordinates and keyed by their
    global grid edge (module docstring)."""
    lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
    box_lo, box_hi = corner + lo, corner + hi
    surface = mesh_box(volume, tuple(int(x) for x in lo), tuple(int(x) for x in hi), min_weight)
    if len(surface.triangles) == 0:
        return empty_slice(box_lo, box_hi)
    keys = np.column_stack([box_lo + surface.edges[:, :3], surface.edges[:, 3]])
    points = volume.voxel_to_world(lo + surface.vertices)
    return SliceMesh(
        points=points.astype(np.float32),
        triangles=surface.triangles,
        colours=surface.colours,
        keys=keys.astype(np.int32),
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
        mesh_box: BoxMesher = marching_cubes.mesh_box,
    ) -> None:
        self.volume = volume
        # The slices' surfaces: the backend's mesh stage's (cuda's on the device, where
        # `volume` lies), or the reference's.
        self.mesh_box = mesh_box
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
        mesh = extract_box(
            self.volume, tuple(lo), tuple(hi), self.corner, self.extract_weight, self.mesh_box
        )
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
        mesh = extract_box(
            self.volume, (0, 0, 0), (n, n, n), self.corner, self.extract_weight, self.mesh_box
        )
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
        mesh = extract_box(
            self.volume, (0, 0, 0), (n, n, n), self.corner, self.extract_weight, self.mesh_box
        )
        if len(mesh.triangles):
            self.store.add(mesh)
        self.finished = True
