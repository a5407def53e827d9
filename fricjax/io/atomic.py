"""Every output file goes through here: built in memory, written to a partial file beside
the target, then renamed onto it (``os.replace``).

A reader sees the old file or the complete new one, never a truncated one. HDF5 files are
built in memory (h5py on a ``BytesIO``) and written with plain Python I/O: a full disk
then surfaces as an ``OSError`` here, where it becomes one line (:class:`OutputFault`,
exit 1) instead of a crash inside the HDF5 library's own writes.

Partial files are named ``.NAME.fricjax-partial-PID`` (hidden, next to ``NAME``): a user
who sees one knows what it is. A run that dies before its rename (kill -9, power loss)
leaves its partial file behind; the next write into the same folder removes partial files
whose process is gone.
"""

from __future__ import annotations

import errno
import io
import os
import re
from collections.abc import Callable, Mapping
from pathlib import Path

import h5py

from fricjax.errors import FricjaxError, OutputFault, where

PARTIAL_TAG = ".fricjax-partial-"
_PARTIAL = re.compile(r"^\..+" + re.escape(PARTIAL_TAG) + r"(\d+)$")


def partial_path(path: Path) -> Path:
    """The partial file of ``path`` for this process: ``DIR/.NAME.fricjax-partial-PID``."""
    return path.with_name(f".{path.name}{PARTIAL_TAG}{os.getpid()}")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def clean_stale(folder: Path) -> list[Path]:
    """Remove partial files in ``folder`` left by processes that no longer exist."""
    removed = []
    try:
        entries = list(folder.iterdir())
    except OSError:
        return removed
    for entry in entries:
        match = _PARTIAL.match(entry.name)
        if match and int(match.group(1)) != os.getpid() and not _alive(int(match.group(1))):
            try:
                entry.unlink()
                removed.append(entry)
            except OSError:
                pass  # not ours to fight over: the write itself does not need it gone
    return removed


def _fault(path: Path, err: OSError) -> OutputFault:
    reason = os.strerror(err.errno) if err.errno else str(err)
    hint = {
        errno.ENOSPC: "; free some space and run again",
        errno.EDQUOT: "; free some space and run again",
        errno.EACCES: "; choose a folder you can write to",
        errno.EPERM: "; choose a folder you can write to",
        errno.EROFS: "; choose a folder you can write to",
    }.get(err.errno or 0, "")
    return OutputFault(f"{where(path)}: cannot write ({reason}){hint}")


def make_folder(folder: str | Path) -> Path:
    """Create ``folder`` (and parents); a file in the way is the user's mistake (exit 2),
    a folder the machine will not create is an :class:`OutputFault` (exit 1)."""
    folder = Path(folder)
    for above in (folder, *folder.parents):
        if above.exists() and not above.is_dir():
            raise FricjaxError(f"{where(above)}: is a file, not a folder (output goes to {folder})")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise _fault(folder, err) from None
    return folder


def _write_fully(fh: io.BufferedWriter, data: bytes) -> None:
    """Write every byte and force it to the disk (a full disk is reported here)."""
    fh.write(data)
    fh.flush()
    os.fsync(fh.fileno())


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (module docstring); returns ``path``.

    Raises:
        FricjaxError: ``path`` is an existing folder, or a file stands where a folder is.
        OutputFault: the machine refused (disk full, read-only folder); nothing is left
            behind and an earlier file at ``path`` is intact.
    """
    path = Path(path)
    if path.is_dir():
        raise FricjaxError(f"{where(path)}: is a folder; give a file name")
    make_folder(path.parent)
    clean_stale(path.parent)
    tmp = partial_path(path)
    try:
        # umask applies as for a plain open(): the result gets the usual permissions
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        with os.fdopen(fd, "wb") as fh:
            _write_fully(fh, data)
        os.replace(tmp, path)
    except OSError as err:
        _discard(tmp)
        raise _fault(path, err) from None
    except BaseException:  # Ctrl-C mid-write: no partial file left behind
        _discard(tmp)
        raise
    return path


def _discard(tmp: Path) -> None:
    try:
        tmp.unlink(missing_ok=True)
    except OSError:
        pass  # the next write into this folder removes it (clean_stale)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """UTF-8 text, atomically (:func:`write_bytes_atomic`)."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def hdf5_bytes(fill: Callable[[h5py.File], None]) -> bytes:
    """The bytes of an HDF5 file built in memory by ``fill(f)``."""
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as f:
        fill(f)
    return buffer.getvalue()


def write_hdf5_atomic(path: str | Path, fill: Callable[[h5py.File], None]) -> Path:
    """An HDF5 file built in memory by ``fill(f)``, written atomically."""
    return write_bytes_atomic(path, hdf5_bytes(fill))


Inputs = Mapping[str, "str | Path | None"]


def _same_file(a: Path, b: Path) -> bool:
    if a.exists() and b.exists():
        return os.path.samefile(a, b)  # hard links and symlinks included
    return a.resolve() == b.resolve()


def _writable_ancestor(path: Path) -> Path | None:
    """The nearest existing folder above ``path`` if it is not writable, else None."""
    for above in path.parents:
        if above.is_dir():
            return None if os.access(above, os.W_OK | os.X_OK) else above
    return None


def check_outputs(outputs: list[Path], inputs: Inputs, flag: str) -> None:
    """Refuse, before any work, outputs that would replace an input or cannot be written.

    ``outputs``: the files a command will write; ``inputs``: what the user gave, by the
    flag or argument that named it (None: not given); ``flag``: the option naming the
    outputs. Inputs are compared as files on disk (``os.path.samefile``: a symlink or
    hard link to an input counts as the input).

    Raises:
        FricjaxError: an output is an input, or an existing folder, or a file stands
            where its folder should be (exit 2).
        OutputFault: the folder exists but this user may not write into it (exit 1).
    """
    for out in map(Path, outputs):
        for label, given in inputs.items():
            if given is not None and _same_file(out, Path(given)):
                raise FricjaxError(
                    f"{where(out)}: {flag} would overwrite the input {label}; "
                    "choose another output path"
                )
        if out.is_dir():
            raise FricjaxError(f"{where(out)}: {flag}: is a folder; give a file name")
        for above in out.parents:
            if above.exists() and not above.is_dir():
                raise FricjaxError(f"{where(above)}: {flag}: is a file, not a folder")
        locked = _writable_ancestor(out)
        if locked is not None:
            raise _fault(out, PermissionError(errno.EACCES, os.strerror(errno.EACCES)))
