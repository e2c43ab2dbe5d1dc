"""Write a file so that readers see either the old complete file or the new complete one.

The content goes to a temporary file in the same folder (same file system), is flushed and
fsync'ed, then renamed over the target: a crash or a full disk mid-write never leaves a
half-written map behind.

Files that belong together (a map's NPZ and its PLYs) are written as one set
(:func:`atomic_file_set`): every file goes to its temporary first, and only when all of
them are written are they renamed over their targets (and the set's stale members
removed); a failure on any of them (a full disk) leaves the old set as it was.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import BinaryIO

__all__ = ['FileSet', 'atomic_file_set', 'atomic_write', 'write_file_set']


def _umask() -> int:
    """The process umask, read without changing it (os.umask would, for every thread)."""
    try:
        with open('/proc/self/status', encoding='ascii') as status:
            for line in status:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    return 0o022


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
    """``with atomic_write(p) as f: f.write(...)``: ``p`` appears only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual file mode
        with os.fdopen(fd, 'wb') as stream:
            yield stream
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


class FileSet:
    """Files staged to be replaced together (see :func:`atomic_file_set`)."""

    def __init__(self) -> None:
        self._staged: list[tuple[str, Path]] = []   # (temporary, target)
        self._stale: list[Path] = []

    @contextlib.contextmanager
    def write(self, path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
        """Like :func:`atomic_write`, but the file is renamed into place with the set."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
        try:
            os.chmod(tmp, 0o666 & ~_umask())
            with os.fdopen(fd, 'wb') as stream:
                yield stream
                stream.flush()
                os.fsync(stream.fileno())
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise
        self._staged.append((tmp, path))

    def remove(self, path: str | os.PathLike[str]) -> None:
        """A member of the set that this version does not have: removed with the commit."""
        self._stale.append(Path(path))

    def commit(self) -> None:
        for tmp, path in self._staged:
            os.replace(tmp, path)
        for path in self._stale:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        for folder in {path.parent for _, path in self._staged}:
            _fsync_folder(folder)
        self._staged = []

    def discard(self) -> None:
        for tmp, _ in self._staged:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        self._staged = []


def _fsync_folder(folder: Path) -> None:
    """The renames themselves reach the disk (a crash right after keeps the new set)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_file_set() -> Iterator[FileSet]:
    """``with atomic_file_set() as files: ... files.write(p1) ... files.write(p2)``: the new
    files replace the old ones only if every one was written; otherwise nothing changes."""
    files = FileSet()
    try:
        yield files
    except BaseException:
        files.discard()
        raise
    files.commit()


def write_file_set(contents: Mapping[Path, bytes | None]) -> list[Path]:
    """Replace the files of ``contents`` together (:func:`atomic_file_set`): each path gets
    its bytes, a path given None is removed (this version of the set has no such member).
    Returns the paths written, in order."""
    written = []
    with atomic_file_set() as files:
        for path, data in contents.items():
            if data is None:
                files.remove(path)
                continue
            with files.write(path) as stream:
                stream.write(data)
            written.append(Path(path))
    return written
