"""Limits the command meets from outside: memory limits that MemAvailable does not show
(`ulimit -v`, cgroups), and signals that end `warmup --empty-cache` while its compile workers
run. docs/reliability.md lists these cases."""

import os
import re
import resource
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from kintinuous_ref import memory

TINY = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"
GiB = 1 << 30


def _fake_proc(root: Path, available_kib: int, vmsize_kib: int, cgroups: str) -> Path:
    (root / "self").mkdir(parents=True)
    (root / "meminfo").write_text(f"MemTotal: 99999999 kB\nMemAvailable: {available_kib} kB\n")
    (root / "self" / "status").write_text(f"Name: python\nVmPeak: 1 kB\nVmSize: {vmsize_kib} kB\n")
    (root / "self" / "cgroup").write_text(cgroups)
    return root


def _write(folder: Path, **files: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (folder / name.replace("_", ".", 1)).write_text(text)


def test_the_tightest_limit_is_memavailable_rlimit_as_or_a_cgroup(tmp_path):
    proc = _fake_proc(tmp_path / "proc", 8 * 1024 * 1024, 1024 * 1024, "0::/user/app\n")
    cgroup = tmp_path / "cgroup"
    # v2: the process's own cgroup has no limit ("max"), the one above it 3 GiB with 1 GiB used
    _write(cgroup / "user" / "app", memory_max="max\n", memory_current=str(GiB))
    _write(cgroup / "user", memory_max=str(3 * GiB), memory_current=str(GiB))
    assert memory.system_free(proc) == memory.Limit(8 * GiB, "MemAvailable in /proc/meminfo")
    assert memory.cgroup_left(proc, cgroup) == [
        memory.Limit(2 * GiB, f"the cgroup limit {cgroup / 'user' / 'memory.max'}")
    ]
    assert memory.tightest(proc, cgroup).bytes == 2 * GiB  # no RLIMIT_AS in the test process
    # RLIMIT_AS of 2.5 GiB with 1 GiB mapped leaves 1.5 GiB
    assert memory.address_space_left(proc, soft_limit=5 * GiB // 2) == [
        memory.Limit(3 * GiB // 2, "the 2.5 GiB address-space limit, ulimit -v")
    ]
    assert memory.address_space_left(proc, soft_limit=resource.RLIM_INFINITY) == []


def test_cgroup_v1_limits_and_no_limits(tmp_path):
    lines = "5:cpu,cpuacct:/x\n4:memory:/docker/abc\n0::/\n"
    proc = _fake_proc(tmp_path / "proc", 8 * 1024 * 1024, 1024, lines)
    cgroup = tmp_path / "cgroup"
    # the container sees its own cgroup as the hierarchy's root: /docker/abc is not there
    _write(
        cgroup / "memory",
        memory_limit_in_bytes=str(GiB),
        memory_usage_in_bytes=str(GiB // 4),
    )
    limit = cgroup / "memory" / "memory.limit_in_bytes"
    assert memory.cgroup_left(proc, cgroup) == [
        memory.Limit(3 * GiB // 4, f"the cgroup limit {limit}")
    ]
    # v1's "no limit" is a number near 2^63; v2's root has no memory.max
    limit.write_text("9223372036854771712\n")
    assert memory.cgroup_left(proc, cgroup) == []
    assert memory.tightest(proc, cgroup) == memory.system_free(proc)
    # a usage above the limit allows nothing, never a negative amount
    _write(cgroup / "memory", memory_limit_in_bytes=str(GiB), memory_usage_in_bytes=str(2 * GiB))
    assert memory.tightest(proc, cgroup).bytes == 0


def _limit_address_space():
    resource.setrlimit(resource.RLIMIT_AS, (3 * GiB, 3 * GiB))


def _reconstruct(out: Path, *extra: str, prelude: str = "") -> subprocess.CompletedProcess:
    """`kintinuous reconstruct` of 2 tiny_desk frames with a 512^3 reference volume (3 GiB) in
    a process allowed 3 GiB of address space; `prelude` runs before the command."""
    code = textwrap.dedent(prelude) + "from kintinuous_ref.program.cli import main\n"
    code += "import sys\nsys.exit(main(sys.argv[1:]))\n"
    argv = [sys.executable, "-c", code, "reconstruct", str(TINY), "--out", str(out)]
    argv += ["--backend", "ref", "--resolution", "512", "--frames", "2"]
    argv += ["--odometry", "groundtruth", *extra]
    return subprocess.run(
        argv, capture_output=True, text=True, timeout=180, preexec_fn=_limit_address_space
    )


def _messages(stderr: str) -> list[str]:
    assert "Traceback" not in stderr, stderr
    return [line for line in re.split(r"[\r\n]", stderr) if line.startswith("kintinuous:")]


def test_a_volume_beyond_ulimit_v_is_refused_before_any_work(tmp_path):
    # MemAvailable alone lets a 3 GiB volume through on any machine with 3 GiB free; the
    # address-space limit does not, and the check says which limit it met.
    result = _reconstruct(tmp_path / "out")
    assert result.returncode == 2, result.stderr
    (line,) = _messages(result.stderr)
    pattern = (
        r"kintinuous: error: a 512\^3 volume needs 3\.0 GiB but only [0-2]\.\d GiB of memory is "
        r"available \(within the 3\.0 GiB address-space limit, ulimit -v\); lower --resolution"
    )
    assert re.fullmatch(pattern, line), line
    assert not (tmp_path / "out").exists()


def test_memory_gone_between_the_check_and_the_allocation_is_one_line(tmp_path):
    # The check is told there is plenty (as when other processes take the memory after it):
    # the volume's allocation meets the limit, in one line with the documented exit status 2.
    prelude = """
        from kintinuous_ref import tsdf
        tsdf.available_memory_bytes = lambda: 1 << 50
    """
    out = tmp_path / "out"
    result = _reconstruct(out, prelude=prelude)
    assert result.returncode == 2, result.stderr
    assert _messages(result.stderr) == [
        "kintinuous: error: a 512^3 volume needs 3.0 GiB: out of memory while allocating it; "
        f"lower --resolution; the 0 frames done are saved in {out}"
    ]
    assert not (out / "crash.log").exists()


def _processes_using(folder: Path) -> dict[int, bytes]:
    """Pid: command line of every live process whose NUMBA_CACHE_DIR lies in `folder` (the
    warm-up's child and its compile workers inherit it from the command)."""
    marker = f"NUMBA_CACHE_DIR={folder}/".encode()
    found = {}
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            if marker in (entry / "environ").read_bytes():
                found[int(entry.name)] = (entry / "cmdline").read_bytes()
        except OSError:  # ended, or not ours
            continue
    return found


def _compile_workers(folder: Path) -> list[int]:
    return [
        pid
        for pid, cmdline in _processes_using(folder).items()
        if b"--multiprocessing-fork" in cmdline and b"resource_tracker" not in cmdline
    ]


@pytest.mark.parametrize(
    ("number", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["SIGTERM", "SIGINT"]
)
def test_a_signal_ends_warmup_empty_cache_with_its_workers_and_its_cache(tmp_path, number, status):
    temporary = tmp_path / "tmp"  # where the command makes its temporary cache
    temporary.mkdir()
    argv = [sys.executable, "-m", "kintinuous_ref.program.cli", "warmup", "--empty-cache"]
    argv += ["--backend", "cpu", "--odometry", "icp"]
    command = subprocess.Popen(
        argv,
        env={**os.environ, "TMPDIR": str(temporary)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while len(_compile_workers(temporary)) < 2:
            assert command.poll() is None, command.communicate()
            assert time.monotonic() < deadline, "the two compile workers never started"
            time.sleep(0.1)
        assert len(list(temporary.glob("kintinuous-numba-cache-*"))) == 1
        command.send_signal(number)
        stdout, stderr = command.communicate(timeout=30)
        assert command.returncode == status, stderr
        name = signal.Signals(number).name
        assert stderr.strip().splitlines() == [f"kintinuous: interrupted by {name}"]
        assert stdout == ""
        assert _processes_using(temporary) == {}  # the child and its workers ended with it
        assert list(temporary.iterdir()) == []  # and its temporary cache went with them
    finally:
        command.kill()
        command.wait()
        for pid in _processes_using(temporary):
            os.kill(pid, signal.SIGKILL)
