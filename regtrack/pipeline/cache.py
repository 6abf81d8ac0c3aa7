"""Content-addressed cache of finished pipeline stages.

A stage's *key* is the SHA-256 of everything it depends on: the content of its input
files, the configuration sections it reads, the keys of the stages before it, the
regtrack version and a digest of the package's Python sources (:func:`code_digest`: a
solver change during development does not bump the version, and a cached simulation of
the old code must not be re-used).  Change one registration setting and
only registration and later stages get new keys; the mesh and the simulations are found
in the cache.

A stage is produced in a temporary folder and renamed into place when it finishes,
together with a ``_complete.json`` marker, so an interrupted run never leaves a stage
folder that a later run would trust (``os.rename`` of a folder is atomic on POSIX).  The
temporary folder's name holds its producer (``.<key>.<host>-<pid>.<random>.part``); a
process killed outright (SIGKILL) leaves it behind, and the next :class:`StageCache` on
the same root removes it once that process is gone (:func:`remove_stale_parts`).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from regtrack import __version__, _io
from regtrack._signals import check_interrupted

log = logging.getLogger(__name__)

MARKER = "_complete.json"
#: The stage cache of ``regtrack run`` and ``regtrack track`` when none is given.
DEFAULT_CACHE = Path(".regtrack-cache")
#: a temporary file or folder of unknown producer older than this is abandoned (s); the
#: atomic file writes of :func:`regtrack._io.atomic_path` last milliseconds
STALE_AGE_S = 3600.0


def _host_tag() -> str:
    import socket

    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def remove_stale_parts(root: str | os.PathLike) -> int:
    """Remove the temporaries (``.*.part*``) a killed run left one level below ``root``
    (``root/<stage>/``) and in ``root`` itself; return how many were removed.

    A folder named by :meth:`StageCache.produce` is removed when its producer ran on this
    host and is no longer alive; any other temporary when older than
    :data:`STALE_AGE_S`.  A live producer's folder (another run sharing the cache) is kept.
    """
    import re

    root = Path(root)
    if not root.is_dir():
        return 0
    own = re.compile(r"^\.[^.]+\.([0-9a-f]{8})-(\d+)\.")
    host, now, removed = _host_tag(), time.time(), 0
    for p in [*root.glob(".*.part*"), *root.glob("*/.*.part*")]:
        m = own.match(p.name)
        try:
            if m:
                stale = m.group(1) == host and not _pid_alive(int(m.group(2)))
            else:
                stale = now - p.stat().st_mtime > STALE_AGE_S
        except OSError:
            continue
        if not stale:
            continue
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed += 1
    if removed:
        log.info("removed %d unfinished temporary file(s)/folder(s) of an interrupted run "
                 "from %s", removed, root)
    return removed


def file_digest(path: str | os.PathLike, pattern: str = "*") -> str:
    """SHA-256 of a file's bytes, or of a folder's files matching ``pattern`` (names and
    bytes, sorted)."""
    p = Path(path)
    h = hashlib.sha256()
    files = sorted(q for q in p.rglob(pattern) if q.is_file()) if p.is_dir() else [p]
    for q in files:
        if p.is_dir():
            h.update(str(q.relative_to(p)).encode())
        with open(q, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 of the regtrack package's ``.py`` files (relative names and bytes, sorted)."""
    return file_digest(Path(__file__).resolve().parents[1], "*.py")


def fingerprint(*parts: Any) -> str:
    """Stable 16-hex-digit key of JSON-serialisable parts (plus the regtrack version and
    :func:`code_digest`)."""
    text = _io.to_json({"version": __version__, "code": code_digest(), "parts": parts}, indent=None)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass
class StageCache:
    """Stage folders under ``root/<stage>/<key>/``; hits and misses are counted."""

    root: Path
    hits: int = 0
    misses: int = 0
    events: list = field(default_factory=list)

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        remove_stale_parts(self.root)

    def folder(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def has(self, stage: str, key: str) -> bool:
        """Whether ``stage`` with ``key`` is finished (not counted as a hit or miss)."""
        return (self.folder(stage, key) / MARKER).is_file()

    def lookup(self, stage: str, key: str) -> Path | None:
        """The finished folder of ``stage`` with ``key``, or None (counted as hit/miss)."""
        d = self.folder(stage, key)
        if (d / MARKER).is_file():
            self.hits += 1
            self.events.append((stage, key, "hit"))
            log.debug("cache hit %s/%s", stage, key)
            return d
        self.misses += 1
        self.events.append((stage, key, "miss"))
        return None

    @contextlib.contextmanager
    def produce(self, stage: str, key: str, *, info: dict | None = None) -> Iterator[Path]:
        """Yield an empty temporary folder; on success it becomes the stage folder."""
        final = self.folder(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key}.{_host_tag()}-{os.getpid()}.", suffix=".part",
                                    dir=final.parent))
        t0 = time.perf_counter()
        try:
            yield tmp
            check_interrupted()  # an interrupted stage is never stored, even if it finished
            _io.write_json(tmp / MARKER, {"stage": stage, "key": key, "seconds": time.perf_counter() - t0,
                                          "version": __version__, "info": info or {}})
            if final.exists():  # produced concurrently by another worker: keep theirs
                shutil.rmtree(tmp)
            else:
                try:
                    os.rename(tmp, final)
                except OSError:
                    if not (final / MARKER).is_file():
                        raise
                    shutil.rmtree(tmp, ignore_errors=True)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def marker(self, stage: str, key: str) -> dict:
        return json.loads((self.folder(stage, key) / MARKER).read_text())

    @property
    def hit_rate(self) -> float:
        n = self.hits + self.misses
        return self.hits / n if n else 0.0
