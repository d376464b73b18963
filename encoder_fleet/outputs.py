"""A command's output file, written whole or not at all."""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

_STREAMS = ("/dev/", "/proc/")  # /dev/stdout, /proc/self/fd/1: written as they are, never replaced


@contextlib.contextmanager
def replaced(path: str | Path, mode: str = "w", *, perms: int | None = None) -> Iterator:
    """A file object on a temporary file beside `path`, renamed onto `path` once the block ends without an error: a
    reader never sees half a file, and a write that fails (a full disk) leaves the file that was there as it was and
    no temporary file behind. The file keeps the mode of the one it replaces (a new one gets the umask's), unless
    `perms` says otherwise; `perms` is set before anything is written (0o600 for a secret: never readable by others,
    not even briefly). A symlink's target is replaced, not the link; a stream (/dev/stdout, a pipe) is written as it
    is."""
    path = Path(path)
    encoding = {} if "b" in mode else {"encoding": "utf-8"}
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory, not a file", str(path))
    target = path.resolve() if path.is_symlink() else path
    if str(path).startswith(_STREAMS) or str(target).startswith(_STREAMS) or (path.exists() and not path.is_file()):
        std = _own_stream(path)
        if std is not None:  # this process's stdout or stderr: through it, in order with what it prints
            std.flush()
            out = std.buffer if "b" in mode else std
            yield out
            out.flush()
            return
        with open(path, mode, **encoding) as out:
            yield out
        return
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:  # a file where a folder of the path should be: say so of the output's own path
        raise NotADirectoryError(errno.ENOTDIR, "a folder of the path is a file", str(path)) from None
    if perms is None:
        perms = stat.S_IMODE(target.stat().st_mode) if target.exists() else 0o666 & ~_umask()
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".part")
    try:
        os.fchmod(fd, perms)
        with os.fdopen(fd, mode, **encoding) as out:
            yield out
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_file(path: str | Path, data: str | bytes, *, perms: int | None = None) -> None:
    """`data` as the whole of the file at `path` (see replaced)."""
    with replaced(path, "wb" if isinstance(data, bytes) else "w", perms=perms) as out:
        out.write(data)


def is_stdout(path: str | Path) -> bool:
    """`path` names this process's stdout (/dev/stdout, /proc/self/fd/1): what the command prints besides goes to
    stderr, or it is mixed into the output."""
    return _own_stream(Path(path)) is sys.stdout


def _own_stream(path: Path):
    """sys.stdout or sys.stderr when the stream `path` names (/dev/stdout, /proc/self/fd/1) is the same file as one."""
    for std in (sys.stdout, sys.stderr):
        try:
            if os.path.samefile(path, f"/proc/self/fd/{std.fileno()}"):
                return std
        except (OSError, ValueError, AttributeError):  # no such file, or a stream with no descriptor (pytest's)
            continue
    return None


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
