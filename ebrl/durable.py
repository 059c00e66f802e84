"""Writing files durably: a crash (kill -9, power loss) at any moment leaves the old file or the whole new one.

The one recipe every module that writes state a run depends on uses (checkpoints, the policy files, the
handover, the replay, secrets, the run directory's records, the machine's caches): the data goes into a
temporary file beside the target, ``.<name>.<random>.tmp`` (hidden; random, so two writers never share one;
ending in ``.tmp``, so what a kill left is found: :func:`temporaries`), which is fsynced and renamed over the
target, and then the directory is fsynced, so that the rename itself survives a crash. An ``exclusive`` file (a
secret) is hard-linked into place instead of renamed: an existing file is never replaced (on a disk without hard
links it is created in place with O_EXCL). A directory built under a temporary name (a training checkpoint) goes
into place with :func:`replace_dir`.

A file is created with ``mode`` as open(2) takes it: the umask applies, so the default 0o666 leaves it to the
umask (0644 under the usual 022), as a plain ``open`` would; 0o600 keeps a secret its owner's.

Standard library only: the bottom layer, importable from anywhere in ebrl.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import os
import secrets
import shutil
from pathlib import Path
from typing import Iterator

SUFFIX = ".tmp"  # every temporary ends so: cleanup finds them (temporaries, ebrl.algos.checkpoint.remove_stale)
_NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS, errno.EMLINK}  # a FAT or FUSE disk


def write_bytes(path: str | os.PathLike, data: bytes, *, mode: int = 0o666, exclusive: bool = False) -> Path:
    """Put ``data`` at ``path`` durably and atomically (readers see the old file or the whole new one); return
    the path. ``exclusive``: an existing file is an error (FileExistsError), never replaced."""
    if not exclusive:
        with writing(path, mode=mode) as tmp:
            tmp.write_bytes(data)
        return Path(path)
    return _create(path, data, mode)


def write_text(path: str | os.PathLike, text: str, *, mode: int = 0o666, exclusive: bool = False) -> Path:
    """:func:`write_bytes` of ``text`` as UTF-8."""
    return write_bytes(path, text.encode(), mode=mode, exclusive=exclusive)


@contextlib.contextmanager
def writing(path: str | os.PathLike, *, mode: int = 0o666) -> Iterator[Path]:
    """A temporary path beside ``path`` to write the new file at (for a writer that takes a filename, such as
    safetensors' ``save_file``; open it for one that takes a file object); when the block ends, the file is
    fsynced, renamed over ``path`` and the directory fsynced. It gets ``mode`` whatever the writer made (safetensors
    writes a file of its own, 0600). An exception in the block removes the temporary and leaves ``path`` as it
    was."""
    path = Path(path)
    tmp = _new_temporary(path, mode)
    try:
        yield tmp
        os.chmod(tmp, mode & ~_umask())
        fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def replace_dir(tmp: str | os.PathLike, final: str | os.PathLike) -> None:
    """Put the directory ``tmp`` (built beside ``final``, named ``*.tmp``, every file in it written) in place of
    ``final``: everything in it and itself fsynced, an existing ``final`` removed, ``tmp`` renamed to ``final``,
    the parent fsynced. A crash leaves ``final`` whole, or (between the removal and the rename) neither: a
    reader must fall back past a missing one."""
    tmp, final = Path(tmp), Path(final)
    for directory, _, files in os.walk(tmp, topdown=False):
        for name in files:
            fsync_file(Path(directory) / name)
        fsync_dir(Path(directory))
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)
    fsync_dir(final.parent)


def temporaries(path: str | os.PathLike) -> list[Path]:
    """The temporary files of writes of ``path`` that did not finish (a kill left them), oldest first."""
    path = Path(os.path.abspath(path))
    found = glob.glob(os.path.join(glob.escape(str(path.parent)), f".{glob.escape(path.name)}.*{SUFFIX}"))
    return sorted((Path(p) for p in found), key=_mtime)


def remove_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove what writers of ``path`` killed in the middle of a write left (:func:`temporaries`); returns it.
    Only for a file one process writes: another writer's write in progress would go too."""
    removed = []
    for stale in temporaries(path):
        with contextlib.suppress(FileNotFoundError):
            stale.unlink()
            removed.append(stale)
    return removed


def fsync_file(path: str | os.PathLike) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def fsync_dir(path: str | os.PathLike) -> None:
    """Make what was created, renamed or removed in the directory ``path`` survive a crash."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _new_temporary(path: Path, mode: int) -> Path:
    while True:  # a name another writer took is drawn again
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}{SUFFIX}")
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode))
            return tmp
        except FileExistsError:
            continue


def _create(path: str | os.PathLike, data: bytes, mode: int) -> Path:
    """A new file at ``path`` holding ``data``, whole once it has its name: written to a temporary and hard-linked
    to ``path`` (which fails where ``path`` exists, with the message opening it with O_EXCL gives)."""
    tmp = _new_temporary(Path(path), mode)
    try:
        tmp.write_bytes(data)
        fsync_file(tmp)
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), os.fspath(path)) from None
        except OSError as exc:
            if exc.errno not in _NO_HARD_LINKS:
                raise
            _create_in_place(path, data, mode)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    fsync_dir(Path(path).parent)
    return Path(path)


def _create_in_place(path: str | os.PathLike, data: bytes, mode: int) -> None:
    """Where the file system has no hard links: the file created with O_EXCL at ``path`` and written there (a
    crash in the middle leaves it short)."""
    with os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode), "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def _umask() -> int:
    """This process's umask, read without changing it (os.umask would, for every thread, for a moment)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def _mtime(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0
