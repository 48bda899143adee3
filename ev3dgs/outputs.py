"""Output files and folders: check them before expensive work, write them atomically, clean up after crashes.

Every command that writes calls `check_output_file` / `check_output_dir` first (exists? a folder where a file
is wanted? writable? enough free space for an estimated size?), so that a bad --out fails in a second with
one line instead of after an hour of rendering or training.

Writers put their data in a temporary file (or folder) beside the target, named `.NAME.tmp-PID[.ext]`, and
rename it at the end (`atomic_path`, `publish`). A killed process leaves that temporary behind;
`remove_stale_temps` deletes the ones whose PID is no longer alive (or, without a PID in the name, that are
older than a day), and never the temporary of a running process. Commands claim their output first
(ev3dgs.claims): one process at a time writes it, and `publish` never replaces an output that appeared
meanwhile.

`H5Sink` is the file object schema.write hands to h5py: see its docstring for why HDF5 must never see a
failed write.
"""
from __future__ import annotations

import contextlib
import errno as _errno
import os
import re
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

from .errors import Ev3dgsError

__all__ = ["OutputError", "os_error_message", "check_output_file", "check_output_dir", "refuse_existing",
           "write_image", "temp_name", "atomic_path", "publish", "remove_stale_temps", "H5Sink", "STALE_AGE_S"]

STALE_AGE_S = 24 * 3600          # a temporary without a PID in its name is stale after this long
_TEMP = re.compile(r"^\.(?P<name>.+)\.tmp-(?P<tag>[A-Za-z0-9_]+?)(?P<ext>\.[A-Za-z0-9]+)?$")


class OutputError(Ev3dgsError):
    """An output cannot be written (not writable, no space, a folder where a file is wanted...).

    `errno` is the operating system's error number when there is one."""

    def __init__(self, message: str, errno: int | None = None):
        super().__init__(message)
        self.errno = errno


def _mb(n: float) -> str:
    """A byte count in the unit that shows it (never '0.0 MB' for a few kilobytes)."""
    n = max(float(n), 0.0)
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} bytes"


def os_error_message(e: OSError, path: str | os.PathLike | None = None) -> str:
    """'PATH: No space left on device (ENOSPC)' from an OSError, with the path it names or `path`."""
    where = e.filename if e.filename is not None else path
    text = e.strerror or str(e)
    code = _errno.errorcode.get(e.errno or -1)
    if code and code not in text:
        text = f"{text} ({code})"
    if getattr(e, "filename2", None):
        where = f"{where} -> {e.filename2}"
    return f"{where}: {text}" if where is not None else text


def _probe(folder: Path) -> None:
    """Create and remove a file in `folder`: the only test that root, read-only mounts and /sys all obey."""
    probe = folder / f".ev3dgs-probe.tmp-{os.getpid()}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return
    except OSError as e:
        raise OutputError(f"cannot write in {folder}: {os_error_message(e, folder).split(': ', 1)[-1]}",
                          e.errno) from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def _existing_ancestor(path: Path) -> Path:
    p = path
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    return p


def _check_space(folder: Path, estimated_bytes: int, what: str) -> None:
    if not estimated_bytes:
        return
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return
    if free < estimated_bytes:
        raise OutputError(f"not enough free space for {what} in {folder}: needs about {_mb(estimated_bytes)}, "
                          f"{_mb(free)} free", _errno.ENOSPC)


def refuse_existing(path: str | os.PathLike, force: bool, option: str = "--out") -> None:
    """Fail (OutputError, EEXIST) if `path` is an existing file or a non-empty folder and not `force`:
    no command silently replaces earlier results. An empty folder is not a result."""
    path = Path(path)
    if force or not (path.exists() or path.is_symlink()):
        return
    if path.is_dir():
        try:
            next(path.iterdir())
        except StopIteration:
            return
        except OSError:
            pass
        raise OutputError(f"{option} {path} is a folder that is not empty; pass --force to replace its "
                          "contents", _errno.EEXIST)
    raise OutputError(f"{option} {path} exists; pass --force to replace it", _errno.EEXIST)


def check_output_file(path: str | os.PathLike, estimated_bytes: int = 0, *, make_parents: bool = False,
                      option: str = "--out", force: bool = True) -> Path:
    """Fail now (OutputError) if `path` cannot take a new file of about `estimated_bytes` bytes.

    An existing file is refused unless `force` (then it is replaced atomically); a folder is always refused.
    The folder must exist unless make_parents (then its nearest existing ancestor must be a writable folder)."""
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{option} {path} is a folder; give a file name", _errno.EISDIR)
    if path.exists() and not path.is_file():
        raise OutputError(f"{option} {path} exists and is not a regular file", _errno.EEXIST)
    refuse_existing(path, force, option)
    parent = path.parent
    if not parent.exists():
        if not make_parents:
            raise OutputError(f"{option}: output folder does not exist: {parent}", _errno.ENOENT)
        parent = _existing_ancestor(parent)
    if not parent.is_dir():
        raise OutputError(f"{option}: {parent} is not a folder", _errno.ENOTDIR)
    _probe(parent)
    _check_space(parent, estimated_bytes, path.name)
    return path


def check_output_dir(path: str | os.PathLike, estimated_bytes: int = 0, *, option: str = "--out",
                     force: bool = True) -> Path:
    """Fail now (OutputError) if `path` cannot be (or become) a writable folder with about `estimated_bytes`
    bytes free. An existing non-empty folder is refused unless `force`; missing parents are created later by
    the writer."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{option} {path} exists and is not a folder", _errno.ENOTDIR)
    refuse_existing(path, force, option)
    base = path if path.exists() else _existing_ancestor(path)
    if not base.is_dir():
        raise OutputError(f"{option}: {base} is not a folder", _errno.ENOTDIR)
    _probe(base)
    _check_space(base, estimated_bytes, str(path))
    return path


def write_image(path: str | os.PathLike, bgr, what: str = "image") -> None:
    """Encode a BGR(A) uint8 image by its file extension (OpenCV) and write the bytes with Python's file I/O, so
    that a full disk or a read-only folder is an OSError naming the file (no libpng message on stderr, no
    half-written file left silently: the caller writes into a temporary folder or name)."""
    import cv2

    path = Path(path)
    ok, data = cv2.imencode(path.suffix or ".png", bgr)
    if not ok:
        raise OutputError(f"cannot write {path}: the {what} encoder failed", _errno.EIO)
    with open(path, "wb") as f:
        f.write(data.tobytes())


def temp_name(path: str | os.PathLike, pid: int | None = None) -> Path:
    """The temporary name beside `path` that `atomic_path` writes and `remove_stale_temps` recognises."""
    path = Path(path)
    return path.with_name(f".{path.name}.tmp-{os.getpid() if pid is None else pid}")


def _is_write_failure(e: BaseException) -> bool:
    if isinstance(e, OSError):
        return True
    text = str(e)
    return isinstance(e, RuntimeError) and ("PytorchStreamWriter" in text or "inline_container" in text
                                            or "file write failed" in text)


def _write_failure(e: BaseException, path: Path) -> OutputError:
    if isinstance(e, OSError):
        return OutputError(f"cannot write {os_error_message(e, path)}", e.errno)
    # torch.save reports a failed write as a RuntimeError from its C++ stream writer ("[enforce fail at
    # inline_container.cc] unexpected pos ...") without the errno: say what the disk says instead
    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        return OutputError(f"cannot write {path}: the write failed", _errno.EIO)
    if free < (16 << 20):
        return OutputError(f"cannot write {path}: No space left on device (ENOSPC), {_mb(free)} free", _errno.ENOSPC)
    return OutputError(f"cannot write {path}: the write failed ({_mb(free)} free on the device)", _errno.EIO)


def publish(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Rename the finished temporary `tmp` to `path`; under this process's claim of `path` without replacing
    an output that appeared meanwhile (ev3dgs.claims.publish)."""
    from .claims import publish as _publish

    _publish(tmp, path)


def _remove(p: Path) -> None:
    with contextlib.suppress(OSError):  # never let the clean-up hide the real error (EROFS, EACCES...)
        os.unlink(p)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it to `path` when the block succeeds.

    On any failure the temporary is removed; a failed write (OSError, or torch's RuntimeError from its
    stream writer) becomes an OutputError naming `path` and the reason (e.g. No space left on device)."""
    path = Path(path)
    tmp = temp_name(path)
    try:
        yield tmp
        publish(tmp, path)
    except BaseException as e:
        _remove(tmp)
        if _is_write_failure(e):
            raise _write_failure(e, path) from None
        raise


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return True
    # a zombie (killed, not yet reaped by its parent) writes nothing any more
    with contextlib.suppress(OSError):
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[-1].split()[0] != "Z"
    return True


def remove_stale_temps(folder: str | os.PathLike, name: str | None = None,
                       max_age_s: float = STALE_AGE_S) -> list[Path]:
    """Delete the temporaries (`.NAME.tmp-PID[.ext]`, files or folders) that dead processes left in `folder`.

    name: only the temporaries of this file name (use it in folders shared with other outputs);
    None = every temporary in the folder. A temporary whose PID is alive is kept; one without a PID
    (a random suffix) is deleted once older than max_age_s. Returns the paths deleted."""
    folder = Path(folder)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        m = _TEMP.match(entry.name)
        if m is None or (name is not None and m["name"] != name):
            continue
        is_dir = entry.is_dir(follow_symlinks=False)  # a folder built under a temporary name (render's frames)
        if not (is_dir or entry.is_file(follow_symlinks=False)):
            continue
        tag = m["tag"]
        if tag.isdigit():
            stale = not _pid_alive(int(tag))
        else:
            try:
                stale = now - entry.stat(follow_symlinks=False).st_mtime > max_age_s
            except OSError:
                continue
        if stale:
            try:
                if is_dir:
                    shutil.rmtree(entry.path)
                else:
                    os.unlink(entry.path)
                removed.append(Path(entry.path))
            except OSError:
                pass
    return removed


class H5Sink:
    """A file object for h5py's `fileobj` driver that never reports a failed write to HDF5.

    Why: when a write fails inside HDF5 (ENOSPC on a full disk), HDF5 cannot flush the dataset's chunk cache
    when the dataset or the file is closed; the failed close leaves half-freed objects behind, and the next
    close of an object of that file (leaving the `with h5py.File` block, or the garbage collector freeing a
    Dataset kept alive by the exception's traceback) dereferences them: a segmentation fault (exit 139) that
    no `except` can catch.

    So HDF5 writes through this object instead. The first OSError is recorded in `error`, and that write and
    all later ones are kept in memory (reads see them), so HDF5 believes every write succeeded and closes
    cleanly. The writer calls `check()` between blocks: it raises OutputError as soon as a write has failed,
    which bounds the memory kept to about one block plus HDF5's caches. The caller then deletes the file."""

    def __init__(self, path: str | os.PathLike, target: str | os.PathLike | None = None):
        self.path = Path(path)
        self.target = Path(target) if target is not None else self.path  # named in the error message
        self.error: OSError | None = None
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o666)
        self._pos = 0
        self._size = 0
        self._kept: list[tuple[int, bytes]] = []

    # the io interface h5py uses
    def seekable(self) -> bool:
        return True

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, pos: int, whence: int = 0) -> int:
        self._pos = pos if whence == 0 else self._pos + pos if whence == 1 else self._size + pos
        return self._pos

    def write(self, data) -> int:
        mv = memoryview(data).cast("B")
        n = len(mv)
        done = 0
        if self.error is None:
            try:
                while done < n:
                    done += os.pwrite(self._fd, mv[done:], self._pos + done)
            except OSError as e:
                self.error = e
        if done < n:
            self._kept.append((self._pos + done, bytes(mv[done:])))
        self._pos += n
        self._size = max(self._size, self._pos)
        return n

    def readinto(self, buf) -> int:
        mv = memoryview(buf).cast("B")
        n = len(mv)
        data = os.pread(self._fd, n, self._pos)
        mv[:len(data)] = data
        if len(data) < n:
            mv[len(data):] = bytes(n - len(data))
        for off, blob in self._kept:
            lo, hi = max(off, self._pos), min(off + len(blob), self._pos + n)
            if lo < hi:
                mv[lo - self._pos:hi - self._pos] = blob[lo - off:hi - off]
        self._pos += n
        return n

    def read(self, n: int = -1) -> bytes:
        n = self._size - self._pos if n is None or n < 0 else n
        b = bytearray(max(0, n))
        self.readinto(b)
        return bytes(b)

    def truncate(self, size: int | None = None) -> int:
        size = self._pos if size is None else size
        if self.error is None:
            try:
                os.ftruncate(self._fd, size)
            except OSError as e:
                self.error = e
        self._size = size
        return size

    def flush(self) -> None:
        pass

    # ours
    def check(self) -> None:
        """Raise OutputError if a write has failed."""
        if self.error is not None:
            raise self.failure()

    def failure(self) -> OutputError:
        e = self.error
        return OutputError(f"cannot write {os_error_message(OSError(e.errno, e.strerror), self.target)}", e.errno)

    def fsync(self) -> None:
        if self.error is None:
            try:
                os.fsync(self._fd)
            except OSError as e:
                self.error = e

    def close(self) -> None:
        if self._fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = -1
        self._kept = []
