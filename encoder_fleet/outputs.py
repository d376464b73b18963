"""A command's output file, written whole or not at all."""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def replaced(path: str | Path, mode: str = "w", *, perms: int = 0o644) -> Iterator:
    """A file object on a temporary file beside `path`, renamed onto `path` once the block ends without an error: a
    reader never sees half a file, and a write that fails (a full disk) leaves the file that was there as it was and
    no temporary file behind. `perms` are set before anything is written (0o600 for a secret: never readable by
    others, not even briefly). A symlink's target is replaced, not the link; what is not a regular file (a pipe,
    /dev/stdout) is written as it is."""
    path = Path(path)
    encoding = {} if "b" in mode else {"encoding": "utf-8"}
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory, not a file", str(path))
    if path.exists() and not path.is_file():
        with open(path, mode, **encoding) as out:
            yield out
        return
    target = path.resolve() if path.is_symlink() else path
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except FileExistsError:  # a file where a folder of the path should be: say so of the output's own path
        raise NotADirectoryError(errno.ENOTDIR, "a folder of the path is a file", str(path)) from None
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


def write_file(path: str | Path, data: str | bytes, *, perms: int = 0o644) -> None:
    """`data` as the whole of the file at `path` (see replaced)."""
    with replaced(path, "wb" if isinstance(data, bytes) else "w", perms=perms) as out:
        out.write(data)
