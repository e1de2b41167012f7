"""One run per output folder, and outputs that appear whole.

A command that writes a folder (`reconstruct`, `table`) holds `locked(folder)` while it works: an
exclusive `fcntl.flock` on LOCK_NAME inside the folder. The kernel drops the lock when its
process ends, however it ends (SIGKILL included), so a lock left by a killed run never blocks the
next one; a second live run into the same folder is refused in one line naming the pid and the
command that hold it. Every output goes through `atomic`: written under a temporary name unique
to the writer in the same folder, then renamed into place, so that no reader ever sees a 0-byte
or half-written file, even while another process writes the same name.

Standard library only: the command line imports it before anything heavy.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import secrets
import shutil
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

from kintinuous_ref.errors import ConfigError

LOCK_NAME = ".kintinuous.lock"  # never an output: the overwrite checks pass over it
_TEMPORARY = re.compile(r"^\..*\.partial-\d+-[0-9a-f]+(\.[^.]*)?$")
# folders this process holds (real path -> how many nested `locked` blocks): a command and the
# function it calls may both lock the same folder
_HELD: dict[str, int] = {}


class FolderInUse(ConfigError):
    """Another live process holds the output folder's lock."""


def check_folder_path(out: str | Path) -> Path:
    """`out` as a Path, refused (ConfigError) when empty or an existing file. Changes nothing."""
    if not str(out).strip():
        raise ConfigError("--out is empty: name an output folder")
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{path}: exists and is not a folder; --out names a folder")
    return path


@contextlib.contextmanager
def locked(out: str | Path, command: str | None = None) -> Iterator[Path]:
    """Hold the output folder `out` (made when missing) for this process while the block runs;
    FolderInUse when another live process holds it. Reentrant within a process. At the end the
    lock file is removed, and the folder too when this call made it and nothing was written."""
    path = check_folder_path(out)
    key = os.path.realpath(path)
    if key in _HELD:
        _HELD[key] += 1
        try:
            yield path
        finally:
            _HELD[key] -= 1
        return
    made = not path.exists()
    try:
        path.mkdir(parents=True, exist_ok=True)
        handle = _lock(path / LOCK_NAME, wait=False)
    except OSError as err:
        raise ConfigError(
            f"{path}: cannot write the output folder ({err.strerror or err})"
        ) from None
    if handle is None:
        raise FolderInUse(
            f"{path}: in use by {holder(path / LOCK_NAME)}; wait for it to end or "
            "choose another --out"
        )
    _HELD[key] = 1
    try:
        _write_holder(handle, command)
        yield path
    finally:
        del _HELD[key]
        _unlock(path / LOCK_NAME, handle)
        if made:
            with contextlib.suppress(OSError):
                path.rmdir()  # only succeeds when empty: a run refused before any output


@contextlib.contextmanager
def waiting_lock(lock: Path) -> Iterator[None]:
    """Hold the lock file `lock`, waiting while another process holds it: for a shared folder
    (a scenario rendered into the cache) that a second run may use once the first is done."""
    lock.parent.mkdir(parents=True, exist_ok=True)
    handle = _lock(lock, wait=True)
    assert handle is not None  # a waiting lock is always granted
    try:
        _write_holder(handle, None)
        yield
    finally:
        _unlock(lock, handle)


@contextlib.contextmanager
def claimed(path: str | Path) -> Iterator[Path]:
    """Hold `path`, a file or folder a command is about to make whole (convert's log or TUM
    folder), while the block runs: an exclusive flock on `.NAME.lock` beside it. FolderInUse when
    another live process holds it: two writers would share one temporary name beside `path`,
    and each would remove or overwrite the other's."""
    path = Path(path)
    whole = Path(os.path.abspath(path))  # "." and "x/.." name the folder they stand for
    if not whole.name:  # the root: it exists, so the writer refuses it
        yield path
        return
    lock = whole.with_name(f".{whole.name}.lock")
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        handle = _lock(lock, wait=False)
    except OSError as err:
        raise ConfigError(f"{path}: cannot write beside it ({err.strerror or err})") from None
    if handle is None:
        raise FolderInUse(
            f"{path}: being written by {holder(lock)}; wait for it to end or choose another output"
        )
    try:
        _write_holder(handle, None)
        yield path
    finally:
        _unlock(lock, handle)


def _lock(lock: Path, wait: bool) -> int | None:
    """An open descriptor of `lock` holding its exclusive flock, or None when another process
    holds it (and not `wait`). A file removed by its holder as it let go is opened anew, so two
    processes can never hold two different files of the same name."""
    while True:
        try:
            handle = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except FileNotFoundError:  # its folder, made by a run that then let it go empty
            lock.parent.mkdir(parents=True, exist_ok=True)
            continue
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
            current = os.stat(lock)
        except BlockingIOError:
            os.close(handle)
            return None
        except FileNotFoundError:
            os.close(handle)
            continue  # removed by its holder as we locked it
        except BaseException:
            os.close(handle)
            raise
        opened = os.fstat(handle)
        if (opened.st_dev, opened.st_ino) == (current.st_dev, current.st_ino):
            return handle
        os.close(handle)


def _write_holder(handle: int, command: str | None) -> None:
    """This process's pid and command line into the lock file, for the refusal's message."""
    words = command if command is not None else " ".join(["kintinuous", *sys.argv[1:]])
    line = f"{os.getpid()} {' '.join(words.split())[:300]}\n"
    os.ftruncate(handle, 0)
    os.write(handle, line.encode("utf-8", "replace"))


def _unlock(lock: Path, handle: int) -> None:
    """Remove the lock file while still holding it, then let go."""
    try:
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()
    finally:
        os.close(handle)


def holder(lock: Path) -> str:
    """Who holds `lock`, as the holder wrote it: 'pid 123 (kintinuous reconstruct ...)'."""
    text = ""
    for _ in range(20):  # the holder writes its line right after locking: wait a moment for it
        with contextlib.suppress(OSError):
            text = lock.read_text(encoding="utf-8", errors="replace").strip()
        if text:
            break
        time.sleep(0.01)
    pid, _, command = text.partition(" ")
    if not pid.isdigit():
        return "another run"
    return f"pid {pid} ({command})" if command else f"pid {pid}"


@contextlib.contextmanager
def atomic(path: str | Path) -> Iterator[Path]:
    """A temporary name beside `path` (same suffix, unique to this writer) to write to; renamed
    to `path` when the block ends, removed when it raises: no reader ever sees half a file."""
    path = Path(path)
    temporary = path.with_name(
        f".{path.stem}.partial-{os.getpid()}-{secrets.token_hex(4)}{path.suffix}"
    )
    try:
        yield temporary
        if not temporary.exists():  # the writer wrote nothing (an empty block)
            temporary.touch()
        os.replace(temporary, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            temporary.unlink()
        if isinstance(err, OSError) and err.filename is None:  # a write's error names no file
            err.filename = str(path)
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    """`text` into `path`, written under a temporary name and renamed."""
    with atomic(path) as temporary:
        temporary.write_text(text)


def is_temporary(name: str) -> bool:
    """Whether `name` is one of `atomic`'s temporary names (a killed writer's leftover)."""
    return bool(_TEMPORARY.match(name))


def remove(folder: Path, names: Iterable[str]) -> None:
    """Remove `names` from `folder` (files, links or whole folders) and the temporaries a killed
    writer left there. Only under `locked(folder)`: then no live writer owns them."""
    for name in names:
        old = folder / name
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old)
        elif old.exists() or old.is_symlink():
            old.unlink()
    for entry in folder.iterdir():
        if is_temporary(entry.name):
            with contextlib.suppress(FileNotFoundError):
                entry.unlink()


def refuse_earlier(folder: Path, found: list[str]) -> ConfigError:
    """The one-line refusal of a folder that holds an earlier result without --overwrite."""
    return ConfigError(
        f"{folder}: holds an earlier result ({', '.join(found)}); pass --overwrite to replace "
        "it, or choose another --out"
    )
