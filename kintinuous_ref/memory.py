"""The memory this process can still allocate: the least of what the system has free
(MemAvailable), what its address-space limit leaves (`ulimit -v`, RLIMIT_AS, against VmSize)
and what its cgroup leaves (v2 memory.max - memory.current, v1 memory.limit_in_bytes -
memory.usage_in_bytes, for its own cgroup and every one above it).

A volume is checked against this before it is allocated: a limit that MemAvailable alone does
not see ends an allocation with a MemoryError (RLIMIT_AS) or the kernel's OOM killer (a cgroup)
half way through a run, where the check refuses it in one line before any work. Standard
library only; every path is a parameter so that tests can point it at a made-up /proc or cgroup.
"""

from __future__ import annotations

import os
import resource
from dataclasses import dataclass
from pathlib import Path

PROC = Path("/proc")
CGROUP = Path("/sys/fs/cgroup")
_UNLIMITED = 1 << 60  # cgroup v1 writes "no limit" as a number near 2^63


@dataclass(frozen=True)
class Limit:
    """Bytes that one limit still allows, and where the limit is set (for messages)."""

    bytes: int
    source: str


def available_bytes(proc: Path = PROC, cgroup: Path = CGROUP) -> int:
    """The bytes this process can still allocate: the least of every limit (module docstring)."""
    return tightest(proc, cgroup).bytes


def tightest(proc: Path = PROC, cgroup: Path = CGROUP) -> Limit:
    """The limit that allows the fewest bytes now, never below 0."""
    limits = [system_free(proc), *address_space_left(proc), *cgroup_left(proc, cgroup)]
    least = min(limits, key=lambda limit: limit.bytes)
    return Limit(max(0, least.bytes), least.source)


def system_free(proc: Path = PROC) -> Limit:
    """Linux's MemAvailable, else the total physical memory."""
    value = _field_kib(proc / "meminfo", "MemAvailable:")
    if value is not None:
        return Limit(value, "MemAvailable in /proc/meminfo")
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return Limit(total, "physical memory")


def address_space_left(proc: Path = PROC, soft_limit: int | None = None) -> list[Limit]:
    """What RLIMIT_AS's soft limit leaves beside what the process maps already (VmSize); none
    without a limit. `soft_limit` replaces getrlimit's (tests)."""
    if soft_limit is None:
        soft_limit = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft_limit == resource.RLIM_INFINITY or soft_limit < 0:
        return []
    mapped = _field_kib(proc / "self" / "status", "VmSize:") or 0
    source = f"the {soft_limit / 2**30:.1f} GiB address-space limit, ulimit -v"
    return [Limit(soft_limit - mapped, source)]


def cgroup_left(proc: Path = PROC, cgroup: Path = CGROUP) -> list[Limit]:
    """What each memory-limited cgroup holding this process still allows (v2 and v1)."""
    limits = []
    for line in _read(proc / "self" / "cgroup").splitlines():
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":  # v2: one unified hierarchy
            limits += _cgroup_limits(cgroup, path, "memory.max", "memory.current")
        elif "memory" in controllers.split(","):  # v1: the memory controller's hierarchy
            limit, usage = "memory.limit_in_bytes", "memory.usage_in_bytes"
            limits += _cgroup_limits(cgroup / "memory", path, limit, usage)
    return limits


def _cgroup_limits(root: Path, path: str, limit_name: str, usage_name: str) -> list[Limit]:
    """Limit minus usage of the cgroup at `path` under `root` and of each one above it. In a
    container the hierarchy's root is often the container's own cgroup, so missing folders on
    the way are passed over."""
    relative = Path(path.strip("/"))
    limits = []
    for part in (relative, *relative.parents):
        here = root / part
        limit, usage = _number(here / limit_name), _number(here / usage_name)
        if limit is not None and usage is not None and limit < _UNLIMITED:
            limits.append(Limit(limit - usage, f"the cgroup limit {here / limit_name}"))
    return limits


def _field_kib(path: Path, name: str) -> int | None:
    """A "Name: N kB" field of a /proc file, in bytes."""
    for line in _read(path).splitlines():
        if line.startswith(name):
            words = line.split()
            return int(words[1]) * 1024 if len(words) > 1 and words[1].isdigit() else None
    return None


def _number(path: Path) -> int | None:
    """A cgroup file's integer; None for "max", a missing file or anything else."""
    text = _read(path).strip()
    return int(text) if text.isdigit() else None


def _read(path: Path) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""
