"""The numbers of the paper's Tables I-VI from run outcomes, and their Markdown layout.

Layout as in the paper (section VII): one row per method; per dataset the median and the maximum;
the ranking score of eq. 16 (metrics.ranking_scores) of the medians and of the maxima in the last
two columns. In Tables I-IV the best value of each column is in bold and the second best in
italics (lower is better everywhere; values equal as printed share their mark). Tables V and
VI (per-frame milliseconds: avg, min, max, std dev) come once per dataset, as the paper's come
for fr1/room.

Failed runs: a cell of a run that failed reads "failed" and the reason is listed under the tables.
The ranking score needs every method's number on a dataset (eq. 16 divides by the sum over the
methods), so a measure's scores are computed over the datasets where every method has a number;
the datasets left out are named under the table, and with none left the scores read "n/a".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from kintinuous_ref.metrics import MetricsError, ranking_scores
from kintinuous_ref.program.evaluation.runs import FAILED, OK, RunOutcome


@dataclass(frozen=True)
class ErrorTable:
    """One of the paper's error tables: a measure per (method, dataset), median and/or max."""

    number: str  # "I"
    title: str
    short: str  # for figure legends
    unit: str
    columns: tuple[tuple[str, str], ...]  # (errors key, column heading)
    ranked: bool


ERROR_TABLES = (
    ErrorTable(
        "I",
        "Absolute trajectory error (ATE), median and maximum translational error",
        "ATE",
        "m",
        (("ate_median", "Median"), ("ate_max", "Max")),
        True,
    ),
    ErrorTable(
        "II",
        "Relative frame-to-frame error, median and maximum translational error",
        "frame-to-frame translation",
        "m",
        (("rpe_trans_median", "Median"), ("rpe_trans_max", "Max")),
        True,
    ),
    ErrorTable(
        "III",
        "Relative frame-to-frame error, median and maximum rotational error",
        "frame-to-frame rotation",
        "deg",
        (("rpe_rot_median_deg", "Median"), ("rpe_rot_max_deg", "Max")),
        True,
    ),
    ErrorTable(
        "IV",
        "Relative root mean square error (RMSE) of drift over 1 s",
        "drift",
        "m/s",
        (("drift_rmse_m_per_s", "RMSE"),),
        False,
    ),
)
RANKED_MEASURES = tuple(key for t in ERROR_TABLES if t.ranked for key, _ in t.columns)
TIMING_TABLES = (
    ("V", "tracker_ms", "Computational performance of the tracker alone (ms per frame)"),
    ("VI", "pipeline_ms", "Computational performance of the full pipeline (ms per frame)"),
)
TIMING_COLUMNS = (("avg", "Avg"), ("min", "Min"), ("max", "Max"), ("std", "Std dev"))


def method_title(method: str) -> str:
    """The paper's spelling: 'fovis/icp+rgbd' -> 'FOVIS/ICP+RGB-D'."""
    return method.upper().replace("RGBD", "RGB-D")


def build_table(
    outcomes: list[RunOutcome], methods: list[str], datasets: dict[str, dict[str, Any]]
) -> dict[str, Any]:
    """Every number of the evaluation, keyed by method and dataset (the content of table.json).

    `datasets`: label -> facts about it (path, frames, ...), in table order.
    """
    runs: dict[str, dict[str, dict[str, Any]]] = {m: {} for m in methods}
    for outcome in outcomes:
        runs[outcome.method][outcome.dataset] = {
            "status": outcome.status,
            "reason": outcome.reason,
            "errors": outcome.errors,
            "tracker_ms": outcome.tracker_ms,
            "pipeline_ms": outcome.pipeline_ms,
            "frames": outcome.frames,
            "tracking_failures": outcome.tracking_failures,
            "seconds": outcome.seconds,
            "out": outcome.out,
        }
    for method in methods:
        for dataset in datasets:
            runs[method].setdefault(dataset, {"status": FAILED, "reason": "not run"})
    ranking = {key: rank(runs, key, methods, list(datasets)) for key in RANKED_MEASURES}
    return {"methods": list(methods), "datasets": datasets, "runs": runs, "ranking": ranking}


def value(run: dict[str, Any], key: str) -> float | None:
    """A run's number for an errors key, None when the run failed or the measure is undefined."""
    if run.get("status") != OK or not run.get("errors"):
        return None
    number = run["errors"].get(key)
    return None if number is None or not math.isfinite(number) else float(number)


def rank(
    runs: dict[str, dict[str, dict[str, Any]]], key: str, methods: list[str], datasets: list[str]
) -> dict[str, Any]:
    """Eq. 16 scores of one measure over the datasets where every method has a number."""
    complete = [d for d in datasets if all(value(runs[m][d], key) is not None for m in methods)]
    excluded = [d for d in datasets if d not in complete]
    result: dict[str, Any] = {"datasets": complete, "excluded": excluded, "scores": None}
    if not complete:
        result["reason"] = "no dataset on which every method has a number"
        return result
    errors = {m: {d: value(runs[m][d], key) for d in complete} for m in methods}
    try:
        result["scores"] = ranking_scores(errors)
    except MetricsError as err:  # e.g. every method exact on a dataset: no shares to compare
        result["reason"] = str(err)
    return result


def marks(values: list[float | None]) -> list[str]:
    """'best', 'second' or '' per value (lower is better; None takes no part).

    Equal values share a mark; 'second' goes to the next larger distinct value, so a column
    with a tie for first has no second.
    """
    distinct = sorted({v for v in values if v is not None})
    best = distinct[0] if distinct else None
    second = distinct[1] if len(distinct) > 1 else None
    return [
        "best" if v is not None and v == best else "second" if v is not None and v == second else ""
        for v in values
    ]


def format_number(number: float | None) -> str:
    """Four decimals as in the paper; tiny numbers in scientific notation so that they stay
    readable (synthetic data can be far more exact than a Kinect)."""
    if number is None:
        return "n/a"
    if number != 0 and abs(number) < 1e-3:
        return f"{number:.2e}"
    return f"{number:.4f}"


def _decorate(text: str, mark: str) -> str:
    return f"**{text}**" if mark == "best" else f"*{text}*" if mark == "second" else text


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _marked_column(numbers: list[float | None], failed: list[bool]) -> list[str]:
    # Ranked as printed: two methods that agree to the digits shown (e.g. a FOVIS switch that
    # never fired) share a mark rather than one being "better" by 1e-9.
    labels = marks([None if n is None else float(format_number(n)) for n in numbers])
    return [
        "failed" if bad else _decorate(format_number(n), label)
        for n, label, bad in zip(numbers, labels, failed, strict=True)
    ]


def error_table_markdown(table: dict[str, Any], spec: ErrorTable) -> list[str]:
    """Lines of one of Tables I-IV."""
    methods, datasets, runs = table["methods"], list(table["datasets"]), table["runs"]
    heading = ["Method"]
    columns: list[list[str]] = []
    for dataset in datasets:
        failed = [runs[m][dataset]["status"] != OK for m in methods]
        for key, name in spec.columns:
            heading.append(f"{dataset} {name}")
            columns.append(_marked_column([value(runs[m][dataset], key) for m in methods], failed))
    notes = []
    if spec.ranked:
        for key, name in spec.columns:
            heading.append(f"Rank score {name}")
            ranking = table["ranking"][key]
            scores = ranking["scores"]
            numbers = [scores[m] if scores else None for m in methods]
            columns.append(_marked_column(numbers, [False] * len(methods)))
            if ranking["excluded"]:
                left_out = ", ".join(ranking["excluded"])
                notes.append(
                    f"Rank score {name} over {', '.join(ranking['datasets']) or 'no dataset'}"
                    f" ({left_out} left out: not every method has a number there)."
                )
            if scores is None:
                notes.append(f"Rank score {name}: n/a ({ranking.get('reason', '')}).")
    lines = [f"### Table {spec.number}: {spec.title} ({spec.unit})", ""]
    lines.append(_row(heading))
    lines.append(_row(["---"] + ["---:"] * (len(heading) - 1)))
    for i, method in enumerate(methods):
        lines.append(_row([method_title(method)] + [column[i] for column in columns]))
    if notes:
        lines += [""] + notes
    return lines + [""]


def timing_table_markdown(table: dict[str, Any], number: str, key: str, title: str) -> list[str]:
    """Lines of Table V or VI: one sub-table per dataset."""
    methods, runs = table["methods"], table["runs"]
    lines = [f"### Table {number}: {title}", ""]
    for dataset in table["datasets"]:
        if all(runs[m][dataset]["status"] != OK for m in methods):
            lines += [f"{dataset}: no run completed.", ""]
            continue
        lines.append(f"{dataset}:")
        lines.append("")
        lines.append(_row(["Method"] + [name for _, name in TIMING_COLUMNS]))
        lines.append(_row(["---"] + ["---:"] * len(TIMING_COLUMNS)))
        for method in methods:
            run = runs[method][dataset]
            if run["status"] != OK:
                cells = ["failed"] * len(TIMING_COLUMNS)
            else:
                cells = [_milliseconds(run[key][stat]) for stat, _ in TIMING_COLUMNS]
            lines.append(_row([method_title(method)] + cells))
        lines.append("")
    return lines


def _milliseconds(number: float | None) -> str:
    return "n/a" if number is None else f"{number:.1f}"


def failures_markdown(table: dict[str, Any]) -> list[str]:
    """Tracking failures per run (frames not fused) and the reasons of failed runs."""
    methods, datasets, runs = table["methods"], list(table["datasets"]), table["runs"]
    lines = ["### Frames whose tracking failed (not fused) / frames run", ""]
    lines.append(_row(["Method", *datasets]))
    lines.append(_row(["---"] + ["---:"] * len(datasets)))
    for method in methods:
        cells = []
        for dataset in datasets:
            run = runs[method][dataset]
            ok = run["status"] == OK
            cells.append(f"{run['tracking_failures']} / {run['frames']}" if ok else "failed")
        lines.append(_row([method_title(method), *cells]))
    failed = [
        f"- {dataset}, {method_title(method)}: {runs[method][dataset]['reason']}"
        for dataset in datasets
        for method in methods
        if runs[method][dataset]["status"] != OK
    ]
    if failed:
        lines += ["", "Failed runs:", "", *failed]
    return lines + [""]


def render_markdown(table: dict[str, Any], header: list[str] | None = None) -> str:
    """table.md: Tables I-VI laid out like the paper's, best in bold, second best in italics."""
    lines = list(header or [])
    for spec in ERROR_TABLES:
        lines += error_table_markdown(table, spec)
    for number, key, title in TIMING_TABLES:
        lines += timing_table_markdown(table, number, key, title)
    lines += failures_markdown(table)
    return "\n".join(lines).rstrip() + "\n"
