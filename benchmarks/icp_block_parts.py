"""Where one ICP iteration's time goes on the CPU, part by part, on one thread.

    python benchmarks/icp_block_parts.py [--points 270000] [--calls 15]

The CPU's ICP sums its rows block by block (odometry/icp/cpu_block.py): the projections into
the model image, the gathers of the model pixels, the rows (tests, point-to-plane row, robust
and depth-noise weights), and their products added into the 6x6 system (sums/cpu.add_block).
This times each part alone over every block of a frame-sized problem, and the whole chunk pass
that the joint loop runs (`icp_chunk`), so that an optimisation can start where the time is.
The scene is synthetic (a wavy wall 1.2-1.8 m in front of a 640x480 camera, its own model, the
current points shifted 5 mm), with the default configuration's weights (Huber, depth noise),
so the numbers need no dataset. Medians of `--calls` calls after one untimed call, ms and ns
per point; the parts run on the calling thread alone (no helper threads).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import numba
import numpy as np

from kintinuous_fast.odometry.icp import cpu_block, robust_terms
from kintinuous_fast.odometry.sums import NV
from kintinuous_fast.odometry.sums.cpu import BLOCK, add_block
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config
from kintinuous_ref.odometry.icp import robust_threshold, voxel_noise

CAMERA = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)


def wavy_wall(camera: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Vertex and normal maps (h, w, 3) float32 of a wall whose depth waves across the image."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    z = 1.5 + 0.3 * np.sin(u / 80.0)
    vertices = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], -1)
    slope = 0.3 / 80.0 * np.cos(u / 80.0) * camera.fx / z  # dz/dx along the rows, roughly
    normals = np.stack([slope, np.zeros_like(z), -np.ones_like(z)], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return vertices.astype(np.float32), normals.astype(np.float32)


@numba.njit
def _project_all(points, to_model, camera, size, work):  # noqa: ANN001, ANN202
    for start in range(0, points.shape[1], BLOCK):
        stop = min(start + BLOCK, points.shape[1])
        cpu_block._project_block(points, start, stop, to_model, camera, size, work[0], work[1])


@numba.njit
def _gather_all(points, mv, mn, work):  # noqa: ANN001, ANN202
    for start in range(0, points.shape[1], BLOCK):
        stop = min(start + BLOCK, points.shape[1])
        cpu_block._gather_model_block(work[0], work[1], stop - start, mv, mn, work[2])


@numba.njit
def _rows_all(points, pose, limits, robust, work):  # noqa: ANN001, ANN202
    for start in range(0, points.shape[1], BLOCK):
        stop = min(start + BLOCK, points.shape[1])
        cpu_block._icp_rows_block(
            points, start, stop, pose, work[0], work[2], limits, robust, work[3], work[4]
        )


@numba.njit
def _add_all(points, work):  # noqa: ANN001, ANN202
    total = np.zeros(NV)
    rows, weighted = work[3].reshape((8, BLOCK)), work[4].reshape((7, BLOCK))
    for start in range(0, points.shape[1], BLOCK):
        add_block(total, weighted, rows, min(BLOCK, points.shape[1] - start))
    return total


@numba.njit
def _chunks_all(points, pose, to_model, mv, mn, camera, limits, robust, out):  # noqa: ANN001, ANN202
    for chunk in range(out.shape[0]):
        cpu_block.icp_chunk(chunk, points, pose, to_model, mv, mn, camera, limits, robust, out)


def median_ms(call: Callable[[], Any], calls: int) -> float:
    """The median wall time of `calls` calls, after one untimed call (compilation, caches)."""
    call()
    times = []
    for _ in range(calls):
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return float(np.median(times)) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=270_000, help="valid current points")
    parser.add_argument("--calls", type=int, default=15)
    args = parser.parse_args()
    mv, mn = wavy_wall(CAMERA)
    columns = np.concatenate([mv.reshape(-1, 3).T, mn.reshape(-1, 3).T])
    points = np.ascontiguousarray(columns[:, : args.points])
    pose = np.eye(4)
    pose[0, 3] = 0.005
    icp = Config().icp
    camera = (CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy)
    limits = (icp.distance_threshold**2, float(np.cos(np.radians(icp.angle_threshold_deg))))
    threshold = robust_threshold(icp.robust_kernel, icp.robust_noise)
    robust = robust_terms(icp.robust_kernel, threshold, voxel_noise(Config().volume.voxel_size))
    work = cpu_block._block_work(mv.dtype)
    out = np.zeros((64, NV))
    size = (CAMERA.width, CAMERA.height)
    parts = {
        "projections": lambda: _project_all(points, pose, camera, size, work),
        "gathers": lambda: _gather_all(points, mv, mn, work),
        "rows": lambda: _rows_all(points, pose, limits, robust, work),
        "products added": lambda: _add_all(points, work),
        "the whole chunk pass": lambda: _chunks_all(
            points, pose, pose, mv, mn, camera, limits, robust, out
        ),
    }
    print(f"{points.shape[1]} points, median of {args.calls} calls, one thread")
    for name, call in parts.items():
        ms = median_ms(call, args.calls)
        print(f"{name:>22}: {ms:6.2f} ms  {ms * 1e6 / points.shape[1]:5.1f} ns per point")


if __name__ == "__main__":
    main()
