# Sourced from the repository root on a bare GPU machine (benchmarks/cuda_device_check.sh and
# one-off device commands): puts the source tree on PYTHONPATH and, where the package is not
# installed, makes its backends discoverable.
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
# The backends are entry points: where the package is not installed (a bare GPU machine, no
# index to install from), a folder with its metadata alone makes them discoverable.
if ! python3 -c "import importlib.metadata as m; m.distribution('kintinuous')" 2>/dev/null; then
    metadata=${TMPDIR:-/tmp}/kintinuous-metadata
    rm -rf "$metadata" && mkdir -p "$metadata"
    python3 - "$metadata" <<'PY'
import pathlib, sys, tomllib
project = tomllib.loads(pathlib.Path("pyproject.toml").read_text())["project"]
info = pathlib.Path(sys.argv[1]) / "kintinuous-0.0.0+source.dist-info"
info.mkdir()
info.joinpath("METADATA").write_text("Metadata-Version: 2.1\nName: kintinuous\nVersion: 0.0.0+source\n")
groups = project["entry-points"]
info.joinpath("entry_points.txt").write_text("".join(
    f"[{group}]\n" + "".join(f"{name} = {target}\n" for name, target in points.items())
    for group, points in groups.items()))
PY
    export PYTHONPATH=$PYTHONPATH:$metadata
fi
# one line per stage from a benchmark's JSON: median ms, and the counter's per-frame traffic
summary() {
    python3 - "$1" <<'PY'
import json, sys
report = json.load(open(sys.argv[1]))
print(f"  fps {report['fps']:.1f}, failures {report['tracking_failures']}, per frame: "
      + ", ".join(f"{k} {v}" for k, v in report.items() if k.endswith("_per_frame")))
for stage, t in report["timing_ms"].items():
    print(f"  {stage:12s} median {t['median']:8.3f} ms  max {t['max']:8.3f}")
PY
}
