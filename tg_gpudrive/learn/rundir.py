"""A training run's directory: one run writes there at a time.

`claim_run_dir` picks where a new run goes (the folder asked for, or NAME-2, NAME-3, ... when it holds an
earlier run) and locks it; `RunLock` is held while a process writes there: a lock file with the holder's PID and host,
created atomically, so a second `train` into the same folder fails at once with a line naming the holder.
A lock left by a process that died (same host, PID gone) is taken over with a warning.
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import sys
from pathlib import Path

log = logging.getLogger(__name__)

RUN_FILES = ("metrics.csv", "checkpoint.pt", "config.json", "curves.png", "target.json")
LOCK = ".lock"


class RunLocked(ValueError):
    """The run directory is being written by another live process."""


def claim_run_dir(path: Path, overwrite: bool) -> tuple[Path, "RunLock"]:
    """The directory a new run writes, with its lock held: `path` if it holds no run, else (without
    --overwrite) the first free `path-2`, `path-3`, ... , said on stderr; with --overwrite the old run's
    files go. A `path` another live run holds is an error, --overwrite or not. Whether a folder holds a
    run is decided under its lock, so two runs started together never share one."""
    k = 1
    while True:
        cand = path if k == 1 else path.with_name(f"{path.name}-{k}")
        try:
            lock = RunLock(cand).__enter__()
        except RunLocked:
            if cand == path:
                raise
            k += 1  # a later name another new run has just taken
            continue
        if not any((cand / f).exists() for f in RUN_FILES):
            break
        if overwrite and cand == path:
            for f in [*RUN_FILES, *(p.name for p in path.glob("events.out.tfevents.*"))]:
                (path / f).unlink(missing_ok=True)
            print(f"tg-gpudrive train: --overwrite: replacing the run in {path}", file=sys.stderr)
            break
        lock.__exit__()
        k += 1
    if cand != path:
        print(f"tg-gpudrive train: {path} holds an earlier run; this run goes to {cand} "
              f"(--overwrite replaces it, --resume {path} continues it)", file=sys.stderr)
    return cand, lock


def _holder(path: Path) -> tuple[int, str] | None:
    """(pid, host) written in the lock file of `path`, None without one (or an unreadable one)."""
    try:
        pid, host = (path / LOCK).read_text().split(maxsplit=1)
        return int(pid), host.strip()
    except (OSError, ValueError):
        return None


def _alive(pid: int, host: str) -> bool:
    if host != socket.gethostname():
        return True  # another machine's process: cannot be checked from here, so it counts as live
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def check_unlocked(path: Path) -> None:
    """Raise RunLocked if a live process holds `path`."""
    held = _holder(path)
    if held is not None and _alive(*held):
        raise RunLocked(f"{path} is being written by another run (PID {held[0]} on {held[1]}; lock file "
                        f"{path / LOCK}); choose another --out, or wait for it to finish")


def _link_or_create(src: Path, dst: Path, text: str) -> None:
    """Hard-link `src` to `dst`; where the filesystem has no hard links, create `dst` exclusively and
    write `text` (FileExistsError either way if `dst` exists)."""
    try:
        os.link(src, dst)
    except FileExistsError:
        raise
    except OSError:
        fd = os.open(dst, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        with os.fdopen(fd, "w") as f:
            f.write(text + "\n")


class RunLock:
    """Held while this process writes the run directory `path` (created if missing)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.file = self.path / LOCK
        self.held = False

    def __enter__(self) -> "RunLock":
        if self.held:  # taken already (claim_run_dir), entered by a `with`
            return self
        self.path.mkdir(parents=True, exist_ok=True)
        me = f"{os.getpid()} {socket.gethostname()}"
        # the lock appears whole or not at all: written beside it, then hard-linked to its name (which
        # fails if it exists), so no one ever reads a lock file without its holder
        mine = self.path / f"{LOCK}.{os.getpid()}"
        mine.write_text(me + "\n")
        try:
            for _ in range(2):
                try:
                    _link_or_create(mine, self.file, me)
                except FileExistsError:
                    check_unlocked(self.path)  # a live holder: the error; else a stale lock to take over
                    log.warning("%s: taking over the lock of a run that is no longer running (%s)", self.path,
                                (self.file.read_text().strip() if self.file.exists() else "gone"))
                    self.file.unlink(missing_ok=True)
                    continue
                self.held = True
                return self
        finally:
            mine.unlink(missing_ok=True)
        raise OSError(errno.EEXIST, f"could not take the lock {self.file}")

    def __exit__(self, *exc) -> None:
        if self.held and _holder(self.path) == (os.getpid(), socket.gethostname()):
            self.file.unlink(missing_ok=True)
        self.held = False
