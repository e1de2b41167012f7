"""The pipeline on the cuda backend keeps its state on the device, and the cuda colour weights
equal the reference's.

Without a GPU the tests run in a child process with numba's CUDA simulator
(NUMBA_ENABLE_CUDASIM=1 must be set before numba is imported), started by
test_equivalence_cuda_pipeline_in_simulator; the simulator runs every CUDA thread as a Python
thread, so the run is tiny: the synthetic desk at 40x30, two pyramid levels, a 24^3 volume over
4 m, two frames, the second tracked by ICP+RGB-D (2 + 1 iterations) against the first frame and
its raycast (tracking error 4 mm of 12 mm motion).

The pipeline's own run on the device (what crosses between host and device in a tracked frame,
the launches, and its poses against the reference's): tests/test_cuda_frame_budget.py, which
uses this module's frames and Crossings.

Tolerances: the colour weights are bit-identical (products of the same float32 factors). The
tracked poses equal the reference backend's to 0.1 mm / 0.01 degree (measured: 0.3 um, 4e-5
degree), the tolerance tests/test_fast_pipeline.py holds the cpu backend to: the volumes differ
only by the int16 / uint8 rounding and the 6x6 systems by the order of float64 sums. The
reference rather than the cpu backend: the child process would compile the cpu kernels whenever
their cache is stale (25-280 s measured while they were being edited), beyond this test's budget.
"""

import copy
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from kintinuous_fast import cuda_is_simulated, cuda_status, load_backend
from kintinuous_ref.colour import colour_weights as ref_colour_weights
from kintinuous_ref.config import (
    ColourConfig,
    Config,
    PreprocessConfig,
    RgbdConfig,
    TrackingConfig,
    VolumeConfig,
)
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.datasets.tum import Frame

WIDTH, HEIGHT, FRAMES = 40, 30, 2
SMALL = 16  # values: a counter, the three repeat flags, a pose, intrinsics, a 3x3 kernel
NV = 30  # values per partial sum of the odometry kernels (odometry/ops.py)
CONFIG = Config(
    volume=VolumeConfig(resolution=24, size=4.0),
    preprocess=PreprocessConfig(bilateral_radius=2, pyramid_levels=2),
    rgbd=RgbdConfig(combined_iterations=(2, 1)),
    # 40x30 has few points per level: a lower bar than 50 pairs, the same for both backends
    tracking=TrackingConfig(min_correspondences=10),
)

on_device = pytest.mark.skipif(
    bool(cuda_status()), reason="no CUDA GPU: runs in the simulator subprocess below"
)


@pytest.mark.skipif(not cuda_status(), reason="CUDA works here: the tests run in this process")
@pytest.mark.cuda_simulator(Path(__file__), "-k", "not in_simulator")
def test_equivalence_cuda_pipeline_in_simulator(cuda_simulator):
    cuda_simulator()


# ----------------------------------------------------------------------------------------------
# Colour weights and the trackers' host-side checks on device frames


@pytest.fixture(scope="module")
def host_frames():
    """The desk's frames preprocessed by the reference (NumPy)."""
    from kintinuous_ref import preprocess

    desk, frames = desk_frames()
    return desk.camera, [
        preprocess.preprocess_frame(frame.colour, frame.depth, desk.camera, CONFIG.preprocess)
        for frame in frames
    ]


def uploaded(frame):  # noqa: ANN001, ANN201
    """A copy of a host PreprocessedFrame with every array on the device."""
    from numba import cuda

    from kintinuous_ref.preprocess import PreprocessedFrame, PyramidLevel

    def up(array):  # noqa: ANN001, ANN202
        return cuda.to_device(array)

    levels = [
        PyramidLevel(
            level.camera,
            up(level.depth),
            up(level.vertices),
            up(level.normals),
            up(level.intensity),
            up(level.intensity_dx),
            up(level.intensity_dy),
        )  # fmt: skip
        for level in frame.levels
    ]
    return PreprocessedFrame(up(frame.colour), levels[0].depth, levels, up(frame.colour_mask))


@on_device
@pytest.mark.parametrize("angle", [True, False], ids=["angle", "no-angle"])
@pytest.mark.parametrize("check", [True, False], ids=["edges", "no-edges"])
def test_equivalence_cuda_colour_weights(host_frames, angle, check):
    from kintinuous_fast.colour import cuda as colour
    from kintinuous_fast.targets.cuda import is_device

    frame = host_frames[1][0]
    assert np.isnan(frame.levels[0].normals).any() and (frame.depth == 0).any()
    assert not frame.colour_mask.all()  # the cases the factors are there for
    config = ColourConfig(angle_weighting=angle, discontinuity_check=check)
    want = ref_colour_weights(frame, config)
    if angle and check:  # host frame in: host weights out (once: each launch costs ~1 s here)
        got = colour.colour_weights(frame, config)
        assert isinstance(got, np.ndarray) and got.dtype == np.float32
        np.testing.assert_array_equal(got, want)
    on_gpu = colour.colour_weights(uploaded(frame), config)  # device in: device out
    assert is_device(on_gpu)
    np.testing.assert_array_equal(on_gpu.copy_to_host(), want)


@on_device
def test_raw_images_go_up_through_pinned_buffers_that_frames_reuse():
    from kintinuous_fast.targets import cuda as target

    backend = load_backend("cuda")
    rng = np.random.default_rng(7)
    depths = [rng.integers(0, 60000, (HEIGHT, WIDTH), dtype=np.uint16) for _ in range(4)]
    colour = rng.integers(0, 256, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    before = dict(target._STAGING)
    for depth in depths:  # a frame's depth, read back, then let go as a pipeline does
        np.testing.assert_array_equal(backend.upload(depth).copy_to_host(), depth)
    on_device = backend.upload(colour)
    np.testing.assert_array_equal(on_device.copy_to_host(), colour)
    added = {key: buffer for key, buffer in target._STAGING.items() if key not in before}
    assert len(added) <= 2  # one pooled depth buffer (reused by every frame), one colour
    assert all(buffer.host.shape[:2] == (HEIGHT, WIDTH) for buffer in added.values())


@on_device
def test_equivalence_cuda_repeated_streams(host_frames):
    from kintinuous_fast.odometry import cuda as kernels
    from kintinuous_ref.odometry import repeated_streams

    first, second = host_frames[1]
    stale_colour = copy.copy(second)
    stale_colour.levels = [copy.copy(level) for level in second.levels]
    stale_colour.levels[0].intensity = first.levels[0].intensity
    blind = copy.copy(first)
    blind.levels = [copy.copy(level) for level in first.levels]
    blind.levels[0].depth = np.zeros_like(first.depth)
    cases = [(first, first), (first, second), (first, stale_colour), (blind, blind), (None, first)]
    for previous, current in cases:
        want = repeated_streams(previous, current)
        on_device = None if previous is None else uploaded(previous)
        assert kernels.repeated_streams(on_device, uploaded(current)) == want
        assert kernels.repeated_streams(previous, current) == want  # host frames: the reference
    assert [repeated_streams(*case) for case in cases] == [
        (True, True), (False, False), (False, True), (False, False), (False, False)
    ]  # fmt: skip


@on_device
def test_cuda_fovis_downloads_each_frame_once(host_frames, monkeypatch):
    """FOVIS runs on the host: what it reads of a device frame (depth and intensity of every
    level) is downloaded once, when the frame is current, and reused when it is previous."""
    from kintinuous_fast.odometry import cuda as kernels

    camera, frames = host_frames
    tracker = kernels.make_tracker("fovis", CONFIG, camera)
    previous, current = uploaded(frames[0]), uploaded(frames[1])
    crossings = Crossings(monkeypatch)
    tracker.track(previous, current, None, np.eye(4))
    assert sorted(crossings.log) == sorted(
        [("down", level.depth.shape) for level in frames[0].levels + frames[1].levels]
        + [("down", level.intensity.shape) for level in frames[0].levels + frames[1].levels]
    )
    following = uploaded(frames[0])
    crossings.log.clear()
    tracker.track(current, following, None, np.eye(4))  # only the new frame crosses
    assert sorted(crossings.log) == sorted(
        [("down", level.depth.shape) for level in frames[0].levels]
        + [("down", level.intensity.shape) for level in frames[0].levels]
    )


# ----------------------------------------------------------------------------------------------
# The pipeline


class Crossings:
    """Every array that crosses the host/device boundary, as (direction, shape, where)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        from numba import cuda

        self.log: list[tuple[str, tuple[int, ...]]] = []
        # positions in the log of the uploads that make the host wait (no stream given)
        self.blocking: list[int] = []
        self._copying_in = 0  # inside an upload: its own copies and reads are not logged again
        upload = cuda.to_device

        def to_device(array, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
            self._log_upload(array, args, kwargs)
            with self._uploading():
                return upload(array, *args, **kwargs)

        monkeypatch.setattr(cuda, "to_device", to_device)
        if cuda_is_simulated():
            from numba.cuda.simulator.cudadrv.devicearray import FakeCUDAArray as device_array

            self._watch_simulator(monkeypatch)
        else:
            from numba.cuda.cudadrv.devicearray import DeviceNDArrayBase as device_array

            self._watch_downloads(monkeypatch, device_array)
        self._watch_copies_in(monkeypatch, device_array)

    def _log_upload(self, array: Any, args: tuple, kwargs: dict) -> None:
        """An upload in the log; one without a stream (to_device's and copy_to_device's first
        argument after the array) among the blocking ones."""
        stream = kwargs.get("stream", args[0] if args else 0)
        if not stream:
            self.blocking.append(len(self.log))
        self.log.append(("up", tuple(np.shape(array))))

    @contextmanager
    def _uploading(self) -> Iterator[None]:
        self._copying_in += 1
        try:
            yield
        finally:
            self._copying_in -= 1

    def _watch_copies_in(self, monkeypatch: pytest.MonkeyPatch, cls: type) -> None:
        """copy_to_device of a host array into an existing device array is an upload (a GPU's
        to_device calls it too: counted once, there)."""
        from kintinuous_fast.targets.cuda import is_device

        copy_in = cls.copy_to_device

        def copy_to_device(array, source, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
            if not self._copying_in and not is_device(source):
                self._log_upload(source, args, kwargs)
            with self._uploading():
                return copy_in(array, source, *args, **kwargs)

        monkeypatch.setattr(cls, "copy_to_device", copy_to_device)

    def _watch_downloads(self, monkeypatch: pytest.MonkeyPatch, cls: type) -> None:
        download = cls.copy_to_host

        def copy_to_host(array, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
            self.log.append(("down", tuple(array.shape)))
            return download(array, *args, **kwargs)

        monkeypatch.setattr(cls, "copy_to_host", copy_to_host)

    def _watch_simulator(self, monkeypatch: pytest.MonkeyPatch) -> None:
        """The simulator's device arrays wrap NumPy arrays and let NumPy read them silently
        (np.asarray, comparisons), which a GPU's would not: those reads count as downloads too,
        and host arrays handed to a kernel (copied in and back on a GPU) as uploads."""
        from numba.cuda.simulator.cudadrv.devicearray import FakeCUDAArray
        from numba.cuda.simulator.kernel import FakeCUDAKernel

        self._watch_downloads(monkeypatch, FakeCUDAArray)
        metadata = {"shape", "dtype", "ndim", "size", "strides", "itemsize", "nbytes", "_ary"}
        attribute = FakeCUDAArray.__getattr__

        def getattr_(array, name):  # noqa: ANN001, ANN202
            if name not in metadata and not self._copying_in:
                self.log.append((f"down (NumPy reads .{name})", tuple(array._ary.shape)))
            return attribute(array, name)

        monkeypatch.setattr(FakeCUDAArray, "__getattr__", getattr_)
        for op in ("__gt__", "__ge__", "__lt__", "__le__", "__eq__", "__ne__", "__mul__"):
            monkeypatch.setattr(FakeCUDAArray, op, self._host_op(getattr(FakeCUDAArray, op), op))
        launch = FakeCUDAKernel.__call__

        def call(kernel, *args):  # noqa: ANN001, ANN002, ANN202
            for arg in () if kernel._device else args:  # launches, not device functions
                if isinstance(arg, np.ndarray) and arg.ndim > 0:
                    self.log.append(("up and down (host array to a kernel)", arg.shape))
            return launch(kernel, *args)

        monkeypatch.setattr(FakeCUDAKernel, "__call__", call)

    def _host_op(self, method, name: str):  # noqa: ANN001, ANN202
        def operator(array, other):  # noqa: ANN001, ANN202
            self.log.append((f"down (NumPy {name})", tuple(array._ary.shape)))
            return method(array, other)

        return operator


def desk_frames(count: int = FRAMES, size: tuple[int, int] = (WIDTH, HEIGHT)) -> tuple:
    desk = make_scenario("desk", frames=count, width=size[0], height=size[1])
    frames = [
        Frame(index, float(desk.trajectory.timestamps[index]), *desk.render(index))
        for index in range(count)
    ]
    return desk, frames


def is_small(shape: tuple[int, ...]) -> bool:
    """A partial-sum table (blocks, NV), or at most SMALL values."""
    return (len(shape) == 2 and shape[1] == NV) or int(np.prod(shape)) <= SMALL


def image_like(shape: tuple[int, ...], size: tuple[int, int] = (WIDTH, HEIGHT)) -> bool:
    """An image or map of some pyramid level of `size` (width, height), or a volume."""
    width, height = size
    levels = {(height >> level, width >> level) for level in range(len(CONFIG.rgbd.iterations))}
    return (
        tuple(shape[:2]) in levels or len(shape) >= 3 and min(shape[:3]) >= CONFIG.volume.resolution
    )
