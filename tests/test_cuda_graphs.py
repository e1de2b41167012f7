"""The cuda backend's launches recorded per segment and replayed (kintinuous_fast/targets/
cuda_graphs.py), and the pooled device buffers that make a frame's launches repeat
(targets.cuda.pooled_array).

Truths: a replay runs the same kernels with the same arguments as launching them one by one, so
results with graphs equal those without, bit for bit in the simulator (which runs blocks in a
fixed order) and within GPU_ORDER_TOLERANCE on a GPU; a segment replays only when every kernel,
grid and argument repeats; a pooled buffer is handed out again only when nothing refers to it.
The pipeline test runs the desk at 40x30 and counts, frame by frame, how each stage's segment
ran: once the two alternating frame buffers exist, every stage (preprocessing, the dense
estimate, the colour weights, integration and the raycast, which read the frame's pose from
device memory) replays every frame, and the pool stops growing.

Without a GPU the tests run in a child process with numba's CUDA simulator, whose "graphs" are
the recorded launches launched again (cuda_graphs' docstring).
"""

from contextlib import nullcontext
from pathlib import Path

import numpy as np
import pytest
from numba import config as numba_config
from numba import cuda

from kintinuous_fast import cuda_status, load_backend
from kintinuous_fast.targets.cuda import kernel

# On a GPU the ICP and RGB-D pair lists fill in the order their atomic slots are taken, which
# changes from run to run, so the float32 sums over them (and the poses) differ in the last bits
# between any two runs; the simulator runs blocks in a fixed order, so there they are equal.
GPU_ORDER_TOLERANCE = 0.0 if numba_config.ENABLE_CUDASIM else 1e-5

on_device = pytest.mark.skipif(
    bool(cuda_status()), reason="no CUDA GPU: runs in the simulator subprocess below"
)


@pytest.mark.skipif(not cuda_status(), reason="CUDA works here: the tests run in this process")
@pytest.mark.cuda_simulator(Path(__file__), "-k", "not in_simulator")
def test_cuda_graphs_in_simulator(cuda_simulator):
    cuda_simulator()


@pytest.fixture
def graphs():
    """Graphs on for the test, every key forgotten before and after."""
    from kintinuous_fast.targets import cuda_graphs

    cuda_graphs.forget()
    cuda_graphs.enable(True)
    yield cuda_graphs
    cuda_graphs.enable(False)
    cuda_graphs.forget()


@kernel
def _add(values, amount):
    i = cuda.grid(1)
    if i < values.shape[0]:
        values[i] += amount


@on_device
def test_pooled_array_is_reused_only_when_unreferenced():
    from kintinuous_fast.targets.cuda import pooled_array

    def take():
        return pooled_array("test pool", (4, 3), np.float32)

    first = take()
    second = take()
    assert second is not first  # the first is still held
    first_id = id(first)
    view = first[1:2]
    del first
    third = take()
    assert id(third) != first_id  # its view keeps the first's memory in use
    del view, third
    assert id(take()) == first_id  # nothing refers to it any more


@on_device
def test_pooled_arrays_come_back_as_a_group_only_when_none_is_referenced():
    from kintinuous_fast.targets.cuda import pooled_arrays

    specs = (((4, 3), "<f4"), ((4, 3), "<f4"), ((2,), "<f8"))
    first = pooled_arrays("test group", specs)
    assert [(a.shape, a.dtype.str) for a in first] == list(specs)
    first_ids = [id(array) for array in first]
    held = first[1]
    del first
    second = pooled_arrays("test group", specs)
    assert not {id(array) for array in second} & set(first_ids)  # one of the first is held
    del second, held
    assert [id(array) for array in pooled_arrays("test group", specs)] == first_ids


@on_device
def test_segment_launches_then_captures_then_replays(graphs):
    from kintinuous_fast.targets import to_host

    add = _add
    values = cuda.to_device(np.zeros(8))

    @graphs.segment
    def twice(amount):
        add[1, 8](values, amount)
        add[1, 8](values, 2 * amount)

    before = graphs.segment_counts().get(twice.__qualname__, [0, 0, 0]).copy()
    for _ in range(4):
        twice(1.0)
    twice(5.0)  # another scalar: another key, launched
    counts = np.subtract(graphs.segment_counts()[twice.__qualname__], before)
    assert counts.tolist() == [2, 1, 2]
    assert np.array_equal(to_host(values), np.full(8, 4 * 3.0 + 15.0))


@on_device
def test_a_signed_segment_replays_without_running_its_launcher(graphs, monkeypatch):
    from kintinuous_fast.targets import TRAFFIC, to_host

    monkeypatch.setattr(graphs.RECORDER, "verify", False)  # as on a GPU
    add = _add
    values = cuda.to_device(np.zeros(8))
    calls = []

    def launcher():
        calls.append(1)
        add[1, 8](values, 1.0)
        add[1, 8](values, 2.0)

    before = graphs.segment_counts().get("adds", [0, 0, 0]).copy()
    launches = TRAFFIC.launches
    for _ in range(4):
        graphs.signed("adds", (values, 1.0, 2.0), launcher)
    counts = np.subtract(graphs.segment_counts()["adds"], before)
    assert counts.tolist() == [1, 1, 2]  # launched, captured, then replayed alone
    assert len(calls) == 2
    assert TRAFFIC.launches - launches == 4 * 2  # the counter still sees every launch
    if not numba_config.ENABLE_CUDASIM:  # the simulator has no graph to replay
        assert np.array_equal(to_host(values), np.full(8, 4 * 3.0))


@on_device
def test_a_signature_that_misses_an_input_is_caught_when_verified(graphs, monkeypatch):
    from kintinuous_fast.targets import to_host

    monkeypatch.setattr(graphs.RECORDER, "verify", True)  # the simulator's default
    add = _add
    values = cuda.to_device(np.zeros(8))
    amounts = iter([1.0, 1.0, 1.0, 5.0])

    def launcher():
        add[1, 8](values, next(amounts))  # the amount is not in the signature

    for _ in range(3):
        graphs.signed("add some", (values,), launcher)
    assert np.array_equal(to_host(values), np.full(8, 3.0))  # verified calls launch
    with pytest.raises(graphs.SignatureMismatch, match="add some"):
        graphs.signed("add some", (values,), launcher)


@on_device
def test_a_refused_capture_launches_one_by_one_from_then_on(graphs, monkeypatch):
    from kintinuous_fast.targets import to_host

    def refuse(launches):  # noqa: ANN001, ANN202
        raise graphs.CaptureFailed("not permitted while capturing")

    monkeypatch.setattr(graphs, "_capture", refuse)
    add = _add
    values = cuda.to_device(np.zeros(8))

    @graphs.segment
    def once(amount):
        add[1, 8](values, amount)

    refused_before = len(graphs.RECORDER.refusals)
    with pytest.warns(UserWarning, match="capture failed") if not refused_before else nullcontext():
        for _ in range(4):
            once(1.0)
    assert graphs.segment_counts()[once.__qualname__] == [4, 0, 0]
    assert graphs.RECORDER.refusals[refused_before:] == ["not permitted while capturing"]
    assert np.array_equal(to_host(values), np.full(8, 4.0))


@on_device
def test_a_download_inside_a_segment_sees_the_launches_before_it(graphs):
    from kintinuous_fast.targets import to_host

    add = _add
    values = cuda.to_device(np.zeros(4))

    @graphs.segment
    def add_and_read():
        add[1, 4](values, 1.0)
        seen = to_host(values)
        add[1, 4](values, 1.0)
        return seen

    assert np.array_equal(add_and_read(), np.ones(4))
    assert np.array_equal(to_host(values), np.full(4, 2.0))


@kernel
def _add_each(values, amounts):
    i = cuda.grid(1)
    if i < values.shape[0]:
        values[i] += amounts[i]


@on_device
def test_uploads_replay_with_the_values_of_each_call(graphs):
    from kintinuous_fast.targets import to_host
    from kintinuous_fast.targets.cuda import copy_up

    add_each = _add_each
    values = cuda.to_device(np.zeros(4))
    amounts = cuda.device_array(4)

    @graphs.segment
    def add_uploaded(host):
        add_each[1, 4](values, copy_up(amounts, host))

    before = graphs.segment_counts().get(add_uploaded.__qualname__, [0, 0, 0]).copy()
    for step in range(1, 5):  # launched, captured, replayed twice: each call's own amounts
        add_uploaded(np.arange(4.0) * step)
    counts = np.subtract(graphs.segment_counts()[add_uploaded.__qualname__], before)
    assert counts.tolist() == [1, 1, 2]
    assert np.array_equal(to_host(values), np.arange(4.0) * (1 + 2 + 3 + 4))


@on_device
def test_a_buffer_uploaded_twice_in_a_segment_feeds_each_launch_its_own_values(graphs):
    from kintinuous_fast.targets import to_host
    from kintinuous_fast.targets.cuda import copy_up

    add_each = _add_each
    values = cuda.to_device(np.zeros(3))
    amounts = cuda.device_array(3)

    @graphs.segment
    def add_twice():
        add_each[1, 3](values, copy_up(amounts, np.ones(3)))
        add_each[1, 3](values, copy_up(amounts, np.full(3, 10.0)))

    for _ in range(3):
        add_twice()
    assert np.array_equal(to_host(values), np.full(3, 33.0))


@on_device
def test_uploads_without_graphs_are_in_stream_order():
    from kintinuous_fast.targets import cuda_graphs, to_host
    from kintinuous_fast.targets.cuda import copy_up

    was_on = cuda_graphs.enabled()
    cuda_graphs.enable(False)
    try:
        values = cuda.to_device(np.zeros(5))
        amounts = cuda.device_array(5)
        for step in range(1, 4):
            _add_each[1, 5](values, copy_up(amounts, np.full(5, float(step))))
        assert np.array_equal(to_host(values), np.full(5, 6.0))
    finally:
        cuda_graphs.enable(was_on)


@on_device
def test_a_host_array_argument_is_never_captured(graphs):
    add = _add
    values = np.zeros(4)

    @graphs.segment
    def add_to_host_array():
        add[1, 4](values, 1.0)

    for _ in range(3):
        add_to_host_array()
    assert graphs.segment_counts()[add_to_host_array.__qualname__] == [3, 0, 0]
    assert np.array_equal(values, np.full(4, 3.0))  # numba copied it back each time


def _integrate_through_a_shift(with_graphs: bool) -> tuple[np.ndarray, list[tuple]]:
    """Five frames fused into a 16^3 volume, its buffer offset and origin moved (what a shift
    sets) before the fourth: (the volume's cells, per frame integration's (launched, captured,
    replayed))."""
    import fast_equivalence as fe

    from kintinuous_fast.targets import cuda_graphs, to_host
    from kintinuous_fast.tsdf import cuda as cuda_tsdf
    from kintinuous_ref.config import VolumeConfig

    cuda_graphs.forget()
    cuda_graphs.enable(with_graphs)
    camera, poses = fe.camera_for(24, 32), fe.moving_poses(5)
    volume = cuda_tsdf.make_volume(VolumeConfig(resolution=16, size=3.0), poses[0])
    depth = cuda.to_device(fe.scene_depth(24, 32, seed=1).astype(np.float32))
    name = cuda_tsdf.integrate.__qualname__
    ways = []
    try:
        for index, pose in enumerate(poses):
            if index == 3:
                volume.offset[:] = (3, 0, 9)
                volume.origin = volume.origin + np.array([0.05, 0.0, -0.02])
            before = list(cuda_graphs.segment_counts().get(name, [0, 0, 0]))
            cuda_tsdf.integrate(volume, depth, pose, camera)
            after = cuda_graphs.segment_counts()[name] if with_graphs else before
            ways.append(tuple(a - b for a, b in zip(after, before, strict=True)))
    finally:
        cuda_graphs.enable(False)
    return to_host(volume.tsdf_weight), ways


@on_device
def test_integration_replays_through_a_shift_of_the_moving_volume():
    plain, _ = _integrate_through_a_shift(with_graphs=False)
    replayed, ways = _integrate_through_a_shift(with_graphs=True)
    assert np.count_nonzero(plain[..., 1]) > 0.02 * plain[..., 1].size  # a real test
    assert np.array_equal(replayed, plain)
    # The first frame and the shift's also upload the placement: the same copy (the same
    # buffers) with other values, so the shift's frame repeats the first frame's key and is
    # captured, and the frame after it replays the graph made before the shift. No key is
    # launched for the new offset: kernel arguments do not change at a shift.
    assert ways == [(1, 0, 0), (1, 0, 0), (0, 1, 0), (0, 1, 0), (0, 0, 1)], ways


def _run_desk(frames_count: int, with_graphs: bool) -> tuple:
    """(poses, per frame {segment: (launched, captured, replayed)}, pool sizes per frame)."""
    from test_fast_cuda_pipeline import CONFIG, desk_frames

    from kintinuous_fast.targets import cuda_graphs
    from kintinuous_fast.targets.cuda import _POOL
    from kintinuous_ref import pipeline

    cuda_graphs.forget()
    cuda_graphs.enable(with_graphs)
    desk, frames = desk_frames(frames_count, (40, 30))
    ways: list[dict] = []
    pooled: list[int] = []

    def after_frame(_result: object) -> None:
        totals = cuda_graphs.segment_counts()
        ways.append({name: tuple(counts) for name, counts in totals.items()})
        pooled.append(sum(len(arrays) for arrays in _POOL.values()))

    try:
        result = pipeline.run(
            frames,
            desk.camera,
            CONFIG,
            "icp+rgbd",
            desk.trajectory,
            backend=load_backend("cuda"),
            progress=after_frame,
        )
    finally:
        cuda_graphs.enable(False)
    return result, ways, pooled


@on_device
def test_pipeline_replays_its_repeating_stages_and_equals_launching():
    frames_count = 8
    plain, _, _ = _run_desk(frames_count, with_graphs=False)
    replayed, ways, pooled = _run_desk(frames_count, with_graphs=True)
    assert replayed.fused == plain.fused == [True] * frames_count, replayed.failure_reasons
    for a, b in zip(replayed.poses, plain.poses, strict=True):
        assert np.allclose(a, b, rtol=0.0, atol=GPU_ORDER_TOLERANCE), np.abs(a - b).max()
    assert np.linalg.norm(plain.poses[-1][:3, 3] - plain.poses[0][:3, 3]) > 0.005  # a motion

    def per_frame(name: str, frame: int) -> tuple:
        now = ways[frame].get(name, (0, 0, 0))
        before = ways[frame - 1].get(name, (0, 0, 0))
        return tuple(int(a - b) for a, b in zip(now, before, strict=True))

    last = frames_count - 1
    stages = ("preprocess", "estimate_dense", "dense estimate", "colour weights", "integrate")
    for stage in (*stages, "fusion", "raycast", "predict_surface", "model pyramid"):
        assert per_frame(stage, last)[:2] == (0, 0), (stage, ways)
        assert per_frame(stage, last - 1)[:2] == (0, 0), (stage, ways)
        assert per_frame(stage, last)[2] >= 1
    assert pooled[-1] == pooled[-3], pooled  # no buffer made in the last frames
    # the benchmark's counter sees the same replays: in the last frame, one graph launch for
    # each segment replayed and nothing else
    replays = sum(per_frame(stage, last)[2] for stage in ways[last])
    assert replayed.traffic["total"][last].graph_replays == replays
    assert {frame.graph_replays for frame in plain.traffic["total"]} == {0}


@pytest.mark.parametrize(
    ("setting", "simulated", "expected"),
    [(None, False, True), (None, True, False), ("0", False, False), ("1", True, True)],
)
def test_graphs_are_on_by_default_on_a_gpu_only(monkeypatch, setting, simulated, expected):
    from kintinuous_fast.targets import cuda_graphs

    monkeypatch.delenv(cuda_graphs.ENVIRONMENT, raising=False)
    if setting is not None:
        monkeypatch.setenv(cuda_graphs.ENVIRONMENT, setting)
    monkeypatch.setattr(cuda_graphs.numba_config, "ENABLE_CUDASIM", simulated)
    assert cuda_graphs.enabled_by_default() is expected


def test_a_segment_key_tells_launches_apart_by_every_part(monkeypatch):
    """Keys are equal (and hash alike) exactly when the kernels, grids, blocks and arguments
    are: a device array by its address, shape, strides and type; a number by its type and
    value (1, 1.0 and True are three keys); a tuple by its items. A host array cannot be held."""
    from types import SimpleNamespace

    from kintinuous_fast.targets import cuda_graphs

    class FakeDeviceArray:  # what a key reads of a numba device array
        def __init__(self, address: int, shape: tuple) -> None:
            self.device_ctypes_pointer = SimpleNamespace(value=address)
            self.shape, self.strides, self.dtype = shape, (8 * shape[-1], 8), np.dtype(float)

        def copy_to_host(self) -> None: ...

    def key(*arguments, grid=4, dispatcher=print):  # noqa: ANN002, ANN001, ANN202
        launches = [cuda_graphs.Launch(dispatcher, grid, 128, 0, arguments)]
        return cuda_graphs._key(launches * 2)

    monkeypatch.setattr(cuda_graphs, "_simulated", lambda: False)
    first, second = FakeDeviceArray(4096, (2, 3)), FakeDeviceArray(8192, (2, 3))
    same = key(first, 1.0, (2, True))
    assert same == key(first, 1.0, (2, True)) and hash(same) == hash(key(first, 1.0, (2, True)))
    others = [
        key(second, 1.0, (2, True)),
        key(first, 1, (2, True)),
        key(first, True, (2, True)),
        key(first, 1.0, (2, 1)),
        key(first, 1.0, (2, True), grid=(4, 1)),
        key(first, 1.0, (2, True), dispatcher=repr),
        key(FakeDeviceArray(4096, (3, 2)), 1.0, (2, True)),
    ]
    assert all(other != same for other in others)
    assert len(set(others)) == len(others)
    with pytest.raises(cuda_graphs.NotCapturable):
        key(np.zeros(3))
