"""`kintinuous table` (kintinuous_ref.program.evaluation): the paper's Tables I-VI from real runs.

One tiny evaluation (2 methods x 2 synthetic sequences of 8 frames at 160x120, plus a sequence
with a corrupt depth image and a folder that does not exist) is run once for the module, through
the command line with 2 processes; the tests then check its tables against independent truths.
The Dask tests share one LocalCluster of two worker processes on 127.0.0.1.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from kintinuous_ref import metrics
from kintinuous_ref.datasets import synthetic
from kintinuous_ref.datasets.tum import read_trajectory
from kintinuous_ref.program.cli import main
from kintinuous_ref.program.evaluation import (
    FAILED,
    OK,
    RunOutcome,
    build_table,
    marks,
    render_markdown,
    timing_statistics,
)
from kintinuous_ref.program.evaluation.figures import top_view_basis

METHODS = ["icp", "fovis/rgbd"]  # a dense tracker and the switching one (with its own FOVIS)
FRAMES = 8
ERROR_KEYS = (
    "ate_median",
    "ate_max",
    "rpe_trans_median",
    "rpe_trans_max",
    "rpe_rot_median_deg",
    "rpe_rot_max_deg",
)


def _outcome(dataset, method, ate_median, status=OK):
    errors = dict.fromkeys(ERROR_KEYS, 1.0) | {"ate_median": ate_median}
    errors["drift_rmse_m_per_s"] = None
    timing = {"avg": 1.0, "min": 1.0, "max": 1.0, "std": 0.0}
    if status != OK:
        return RunOutcome(dataset, method, FAILED, reason="tracker diverged")
    return RunOutcome(dataset, method, OK, errors=errors, tracker_ms=timing, pipeline_ms=timing)


def _row(markdown, table_number, method_title):
    """The cells of one method's row in one table of table.md."""
    section = markdown.split(f"### Table {table_number}:")[1].split("###")[0]
    for line in section.splitlines():
        if line.startswith(f"| {method_title} |"):
            return [cell.strip() for cell in line.strip("|").split("|")][1:]
    raise AssertionError(f"no row {method_title} in table {table_number}")


# --- Ranking and marks on hand-computed examples (no runs) -------------------------------------


def test_marks_bold_best_italic_second_ties_share():
    assert marks([3.0, 1.0, 2.0, None]) == ["", "best", "second", ""]
    # A tie for the best: both bold; the next distinct value is the second.
    assert marks([1.0, 1.0, 2.0]) == ["best", "best", "second"]
    assert marks([None, None]) == ["", ""]


def test_table_ranks_by_eq16_and_marks_the_cells():
    # ATE medians E(A, D), chosen by hand:        d1 (sum 8)   d2 (sum 10)
    #   A: 1, 5  -> S = (1/8 + 5/10) / 2 = 0.3125      1            5
    #   B: 3, 2  -> S = (3/8 + 2/10) / 2 = 0.2875      3            2
    #   C: 4, 3  -> S = (4/8 + 3/10) / 2 = 0.4         4            3
    # d3: C failed there, so eq. 16 (a share of the sum over all methods) cannot include d3.
    values = {"icp": (1.0, 5.0, 0.1), "rgbd": (3.0, 2.0, 0.1), "fovis": (4.0, 3.0, None)}
    outcomes = []
    for method, (d1, d2, d3) in values.items():
        outcomes.append(_outcome("d1", method, d1))
        outcomes.append(_outcome("d2", method, d2))
        outcomes.append(_outcome("d3", method, d3, OK if d3 is not None else FAILED))
    datasets = {d: {} for d in ("d1", "d2", "d3")}
    table = build_table(outcomes, list(values), datasets)

    ranking = table["ranking"]["ate_median"]
    assert ranking["datasets"] == ["d1", "d2"] and ranking["excluded"] == ["d3"]
    expected = {"icp": 0.3125, "rgbd": 0.2875, "fovis": 0.4}
    assert ranking["scores"] == pytest.approx(expected, abs=1e-12)

    markdown = render_markdown(table)
    # Columns: d1 Median, d1 Max, d2 Median, d2 Max, d3 Median, d3 Max, score Median, score Max.
    icp, rgbd, fovis = (_row(markdown, "I", t) for t in ("ICP", "RGB-D", "FOVIS"))
    assert (icp[0], rgbd[0], fovis[0]) == ("**1.0000**", "*3.0000*", "4.0000")  # d1 median
    assert (icp[2], rgbd[2], fovis[2]) == ("5.0000", "**2.0000**", "*3.0000*")  # d2 median
    assert (icp[6], rgbd[6], fovis[6]) == ("*0.3125*", "**0.2875**", "0.4000")  # scores
    assert fovis[4] == "failed" and "FOVIS: tracker diverged" in markdown
    assert "d3 left out" in markdown
    # Every method has 1.0 for the maxima: equal shares of 1/3, all tied for best.
    assert icp[7] == rgbd[7] == fovis[7] == "**0.3333**"


def test_timing_statistics_match_numpy():
    samples = [12.0, 9.5, 30.25, 11.0]
    stats = timing_statistics(samples)
    assert stats["avg"] == pytest.approx(np.mean(samples), rel=1e-12)
    assert (stats["min"], stats["max"]) == (9.5, 30.25)
    # Population standard deviation: sqrt(mean((x - mean)^2)), computed here by hand.
    mean = sum(samples) / 4
    assert stats["std"] == pytest.approx((sum((x - mean) ** 2 for x in samples) / 4) ** 0.5)
    assert timing_statistics([])["avg"] is None


def test_top_view_is_horizontal_for_an_upright_camera():
    # A camera held upright in a z-up world: its image y axis (down) is world -z.
    # Camera axes in world: x = east (1,0,0), y = down (0,0,-1), z = ahead = north (0,1,0).
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=float)
    basis = top_view_basis(np.stack([pose, pose]))
    # Plot x = heading (north), plot y = up x heading = west: the plane z = const.
    np.testing.assert_allclose(basis, [[0, 1, 0], [-1, 0, 0]], atol=1e-12)


# --- One tiny evaluation through the command line ----------------------------------------------


@pytest.fixture(scope="module")
def evaluation(tmp_path_factory):
    root = tmp_path_factory.mktemp("table")
    folders = []
    for name in ("desk", "corridor"):
        folders.append(
            synthetic.write_scenario(name, root / name, frames=FRAMES, width=160, height=120)
        )
    # A copy of the desk whose 4th depth image is not a PNG: its runs fail at frame 3.
    corrupt = root / "corrupt"
    shutil.copytree(folders[0], corrupt)
    depth_name = (corrupt / "associations.txt").read_text().splitlines()[3].split()[3]
    (corrupt / depth_name).write_bytes(b"not an image")
    missing = root / "missing"  # no such folder
    out = root / "out"
    argv = [
        "table",
        *(str(f) for f in folders),
        str(corrupt),
        str(missing),
        "--methods",
        *METHODS,
        "--out",
        str(out),
        "--jobs",
        "2",
        "--resolution",
        "64",
        "--backend",
        "ref",
    ]
    status = main(argv)
    return {"status": status, "out": out, "folders": folders}


def test_table_has_every_cell(evaluation):
    assert evaluation["status"] == 1  # the corrupt and missing datasets' runs failed
    table = json.loads((evaluation["out"] / "table.json").read_text())
    assert table["methods"] == METHODS
    assert list(table["datasets"]) == ["desk", "corridor", "corrupt", "missing"]
    for method in METHODS:
        for dataset in ("desk", "corridor"):
            run = table["runs"][method][dataset]
            assert run["status"] == "ok", run["reason"]
            assert run["frames"] == FRAMES
            assert all(np.isfinite(run["errors"][key]) for key in ERROR_KEYS)
            # 8 frames span 0.23 s: no pose pair is 1 s apart, so there is no drift to report.
            assert run["errors"]["drift_rmse_m_per_s"] is None
            for timing in (run["tracker_ms"], run["pipeline_ms"]):
                assert 0 < timing["min"] <= timing["avg"] <= timing["max"]
    for key in ERROR_KEYS:
        ranking = table["ranking"][key]
        assert ranking["datasets"] == ["desk", "corridor"]
        assert sum(ranking["scores"].values()) == pytest.approx(1.0)  # eq. 16 shares add up
    markdown = (evaluation["out"] / "table.md").read_text()
    for number in ("I", "II", "III"):
        for title in ("ICP", "FOVIS/RGB-D"):
            cells = _row(markdown, number, title)
            assert len(cells) == 4 * 2 + 2  # 4 datasets x (median, max) + 2 rank scores
            assert "n/a" not in cells[:4] + cells[-2:]
    assert _row(markdown, "IV", "ICP")[:2] == ["n/a", "n/a"]
    for name in ("fig4_ranking_median.png", "fig5_ranking_max.png", "trajectories.png"):
        assert (evaluation["out"] / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_table_numbers_equal_metrics_of_the_written_trajectories(evaluation):
    table = json.loads((evaluation["out"] / "table.json").read_text())
    markdown = (evaluation["out"] / "table.md").read_text()
    for dataset, folder in zip(("desk", "corridor"), evaluation["folders"], strict=True):
        truth = read_trajectory(folder / "groundtruth.txt")
        for method in METHODS:
            run_folder = evaluation["out"] / "runs" / dataset / method.replace("/", "_")
            estimate = read_trajectory(run_folder / "trajectory.txt")
            assert len(estimate) == FRAMES
            expected = metrics.evaluate(estimate, truth).as_dict()
            errors = table["runs"][method][dataset]["errors"]
            # trajectory.txt holds poses to 1e-9 (positions, quaternions): 1e-7 m / deg is ample.
            for key in ERROR_KEYS:
                assert errors[key] == pytest.approx(expected[key], abs=1e-7), key
            # table.md shows the same numbers to four decimals.
            index = 2 * list(table["datasets"]).index(dataset)
            title = "ICP" if method == "icp" else "FOVIS/RGB-D"
            cell = _row(markdown, "I", title)[index].strip("*")
            assert float(cell) == pytest.approx(expected["ate_median"], abs=5e-5)
            # Tables V and VI: statistics of the raw per-frame times in report.json, the first
            # (untracked) frame left out.
            report = json.loads((run_folder / "report.json").read_text())
            for key, stage in (("tracker_ms", "odometry"), ("pipeline_ms", "total")):
                raw = np.array(report["timings_ms"][stage][1:])
                stats = table["runs"][method][dataset][key]
                assert stats["avg"] == pytest.approx(raw.mean(), rel=1e-9)
                assert stats["std"] == pytest.approx(raw.std(), rel=1e-9, abs=1e-12)
                assert (stats["min"], stats["max"]) == (raw.min(), raw.max())


def test_failed_runs_are_reported_not_fatal(evaluation):
    table = json.loads((evaluation["out"] / "table.json").read_text())
    markdown = (evaluation["out"] / "table.md").read_text()
    for method in METHODS:
        corrupt = table["runs"][method]["corrupt"]
        assert corrupt["status"] == "failed"
        assert "cannot read depth image" in corrupt["reason"]  # the DatasetError of frame 3
        missing = table["runs"][method]["missing"]
        assert missing["status"] == "failed"
        assert "neither a dataset folder nor a scenario" in missing["reason"]
        # Every failed run still has its folder with the reason.
        for dataset in ("corrupt", "missing"):
            folder = evaluation["out"] / "runs" / dataset / method.replace("/", "_")
            report = json.loads((folder / "report.json").read_text())
            assert report["status"] == "failed"
            assert report["reason"] == table["runs"][method][dataset]["reason"]
    cells = _row(markdown, "I", "ICP")
    assert cells[4:8] == ["failed"] * 4
    assert "corrupt, ICP: " in markdown and "missing, FOVIS/RGB-D: " in markdown
    assert "corrupt, missing left out" in markdown


def test_bad_options_are_one_line_errors(tmp_path, capsys, monkeypatch):
    import kintinuous_fast

    cases = [
        (["--size", "320by240"], "--size expects WIDTHxHEIGHT"),
        (["--jobs", "0"], "--jobs must be at least 1"),
        (["--frames", "1"], "--frames >= 2"),
        (["--methods", "icp", "icp"], "a method is named twice"),
    ]
    if kintinuous_fast.backend_status()["cuda"]:  # only where CUDA does not work here
        cases.append((["--backend", "cuda"], "backend 'cuda' does not work on this machine"))
    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path))  # never render a scenario here
    for options, message in cases:
        status = main(["table", "desk", "--out", str(tmp_path / "x"), *options])
        error = capsys.readouterr().err
        assert status == 2 and message in error and error.count("\n") == 1, error
    assert not (tmp_path / "desk").exists()  # refused before any dataset was opened


def test_scheduler_without_dask_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    # A module set to None in sys.modules cannot be imported: this is how dask looks when absent.
    monkeypatch.setitem(sys.modules, "dask", None)
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    status = main(["table", "desk", "--out", str(tmp_path), "--scheduler", "tcp://127.0.0.1:1"])
    error = capsys.readouterr().err
    assert status == 2 and error.count("\n") == 1
    assert "needs dask.distributed" in error and "kintinuous[dask]" in error
    assert not Path(tmp_path / "table.md").exists()


# --- The same runs on a Dask cluster --------------------------------------------------------


@pytest.fixture(scope="module")
def cluster():
    """Two single-threaded worker processes on this machine, shared by the tests below. The
    [test] extra installs dask[distributed], so these tests run rather than skip.

    The workers run numba with one thread (and BLAS with one, Dask's default for its workers)
    while this process uses every core: a cluster's machines rarely have the same core count as
    the client's, and the runs must not depend on it."""
    import distributed

    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
        env={"NUMBA_NUM_THREADS": "1"},
    ) as local_cluster:
        yield local_cluster


@pytest.mark.parametrize("backend", ["ref", "cpu"])
def test_cluster_runs_equal_local_runs_bit_for_bit(evaluation, cluster, tmp_path, backend):
    from kintinuous_ref.config import Config, VolumeConfig
    from kintinuous_ref.program.evaluation import evaluate_methods

    # The module's evaluation at --resolution 64: the same volume, methods and frames.
    config = Config(volume=VolumeConfig(resolution=64))
    options = {"methods": METHODS, "config": config, "backend": backend}
    desk = [str(evaluation["folders"][0])]
    local = evaluate_methods(desk, tmp_path / "local", jobs=1, **options)
    scheduler = cluster.scheduler_address
    remote = evaluate_methods(desk, tmp_path / "dask", scheduler=scheduler, **options)
    truth = read_trajectory(evaluation["folders"][0] / "groundtruth.txt")
    for here, there in zip(local.outcomes, remote.outcomes, strict=True):
        assert there.method == here.method
        assert (here.status, there.status) == (OK, OK), (here.reason, there.reason)
        assert here.frames == there.frames == FRAMES
        np.testing.assert_array_equal(there.timestamps, truth.timestamps[:FRAMES])
        assert np.array_equal(here.poses, there.poses), here.method
        assert here.errors == there.errors, here.method
        # Tracked, not copied from the ground truth: the errors are real and not all zero.
        assert here.errors["ate_max"] > 0
        if backend == "ref":
            # The module's --jobs 2 run (spawned processes) wrote the same numbers to table.json;
            # JSON keeps a float64 to the last bit.
            table = json.loads((evaluation["out"] / "table.json").read_text())
            assert table["runs"][here.method]["desk"]["errors"] == there.errors


def test_a_worker_that_cannot_see_the_dataset_says_so_by_name(cluster, tmp_path):
    from kintinuous_ref.config import Config
    from kintinuous_ref.program.evaluation import RunSpec, execute

    # A folder that the client saw and the workers do not: here one that exists nowhere.
    unseen = tmp_path / "mounted-on-the-client-only"
    spec = RunSpec("desk", str(unseen), "icp", str(tmp_path / "run"), Config())
    [outcome] = execute([spec], scheduler=cluster.scheduler_address)
    # The workers' addresses as the scheduler knows them; the run went to one of them.
    workers = sorted(cluster.scheduler_info["workers"])
    assert len(workers) == 2 and all(w.startswith("tcp://127.0.0.1:") for w in workers)
    expected = [
        f"worker {worker} cannot see the dataset folder {unseen} "
        "(every worker needs the datasets at the client's paths)"
        for worker in workers
    ]
    assert (outcome.dataset, outcome.method, outcome.status) == ("desk", "icp", FAILED)
    assert outcome.reason in expected
    assert outcome.poses is None and outcome.errors is None
    # The worker also left the reason in the run's folder, as for any failed run.
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert (report["status"], report["reason"]) == (FAILED, outcome.reason)
    assert report["path"] == str(unseen)


def test_relative_paths_on_a_cluster_are_the_clients(evaluation, cluster, tmp_path, monkeypatch):
    from kintinuous_ref.config import Config, VolumeConfig
    from kintinuous_ref.program.evaluation import RunSpec, execute

    # The workers started in the folder pytest runs from; the client now works in another one.
    shutil.copytree(evaluation["folders"][0], tmp_path / "desk")
    monkeypatch.chdir(tmp_path)
    config = Config(volume=VolumeConfig(resolution=64))
    spec = RunSpec("desk", "desk", "icp", str(Path("runs", "icp")), config)
    [outcome] = execute([spec], scheduler=cluster.scheduler_address)
    assert outcome.status == OK, outcome.reason
    assert outcome.out == str(tmp_path / "runs" / "icp")
    assert len(read_trajectory(tmp_path / "runs" / "icp" / "trajectory.txt")) == FRAMES
    # The same run as the module's icp run on the desk: the same errors, to the last bit.
    table = json.loads((evaluation["out"] / "table.json").read_text())
    assert outcome.errors == table["runs"]["icp"]["desk"]["errors"]


def test_table_reproduces_the_papers_published_rank_scores():
    # The paper's own medians and maxima (Tables I-III, transcribed in evaluation.paper) through
    # build_table give its published eq. 16 scores: an independent check of the ranking and of the
    # transcription. Inputs are printed to 3-4 digits, scores to 4 decimals: 1e-4 allows for both.
    from kintinuous_ref.program.evaluation import paper

    table = paper.as_table()
    for key, published in paper.RANK_SCORES.items():
        assert table["ranking"][key]["datasets"] == list(paper.DATASETS)
        assert table["ranking"][key]["scores"] == pytest.approx(published, abs=1e-4), key
    # The paper's text: ICP+RGB-D ranks first in consistency of the median errors (Table I).
    markdown = render_markdown(table)
    assert _row(markdown, "I", "ICP+RGB-D")[-2] == "**0.0904**"
    assert _row(markdown, "I", "FOVIS/ICP+RGB-D")[-2] == "*0.0911*"


def test_values_equal_as_printed_share_their_mark():
    # 0.00123 and 0.001234 both print as 0.0012: neither is shown as better than the other.
    outcomes = [
        _outcome("d1", "icp", 0.00123),
        _outcome("d1", "rgbd", 0.001234),
        _outcome("d1", "fovis", 0.0031),
    ]
    markdown = render_markdown(build_table(outcomes, ["icp", "rgbd", "fovis"], {"d1": {}}))
    cells = [_row(markdown, "I", title)[0] for title in ("ICP", "RGB-D", "FOVIS")]
    assert cells == ["**0.0012**", "**0.0012**", "*0.0031*"]
