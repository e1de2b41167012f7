"""The command line's defaults agree with the README: `reconstruct` tracks with the paper's
ICP+RGB-D odometry, and `table` runs on the same `auto` backend as `reconstruct`."""

import re
from pathlib import Path

from kintinuous_ref.odometry import DEFAULT_METHOD
from kintinuous_ref.program.cli import build_parser

README = Path(__file__).resolve().parent.parent / "README.md"


def test_reconstruct_defaults_to_the_papers_icp_rgbd_as_the_readme_says():
    args = build_parser().parse_args(["reconstruct", "--out", "o"])
    assert args.odometry == DEFAULT_METHOD == "icp+rgbd"
    assert build_parser().parse_args(["benchmark"]).odometry == DEFAULT_METHOD
    assert re.search(r"`icp\+rgbd` \(default\)", README.read_text())


def test_table_defaults_to_the_auto_backend_like_reconstruct():
    parser = build_parser()
    table = parser.parse_args(["table", "desk"])
    reconstruct = parser.parse_args(["reconstruct", "--out", "o"])
    assert table.backend == reconstruct.backend == "auto"


def test_fast_odometry_help_quotes_no_numbers_that_can_go_stale():
    """Its measurements live in docs/benchmarks.md, with the run that produced them."""
    from kintinuous_ref.program.cli import FAST_ODOMETRY_HELP

    assert not re.search(r"\d", FAST_ODOMETRY_HELP)
    assert "docs/benchmarks.md" in FAST_ODOMETRY_HELP
