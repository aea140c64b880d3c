"""Writing files so that an interrupted write never leaves half of one: frames
(:meth:`glossrt.frame.Frame.save`), BSPVT trees (:meth:`glossrt.lights.bspvt.build.BSPVT.save`) and
the command line's JSON outputs all go through :func:`replacing`."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator

__all__ = ["FolderNotWritable", "replacing"]


class FolderNotWritable(OSError):
    """The temporary file next to the target could not be created."""


@contextlib.contextmanager
def replacing(path: str | os.PathLike[str]) -> Iterator[str]:
    """A temporary file name in ``path``'s folder to write to; when the block ends normally
    the file gets mode 0644 and is renamed over ``path``, when it raises the file is removed
    and ``path`` is left as it was. :class:`FolderNotWritable` when the temporary file cannot
    be created."""
    folder, name = os.path.split(os.path.abspath(os.fspath(path)))
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
    except OSError as e:
        raise FolderNotWritable(e.errno, e.strerror, folder) from e
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
