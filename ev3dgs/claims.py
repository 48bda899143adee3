"""Output claims: one ev3dgs process at a time writes an output; what it publishes replaces nothing it did not
mean to replace.

A command claims its output before any work: `claim_output(path)` for a file or a folder built under a
temporary name (a claim file `.NAME.claim` beside it), `claim_run(folder)` for a folder written in place, such
as a training run (a lock file `.ev3dgs.lock` inside it). A claim is created atomically (written under a
temporary name and hard-linked to the claim's name, which fails when the name exists; O_CREAT|O_EXCL where the
file system has no hard links), so of two processes exactly one gets it; the other stops with one line naming
the holder: PID, host, start time and command. The temporaries a killed writer of the output left are removed
once the claim is held. The existence check (`--force`) runs again once the claim is
held, so an output finished between a command's first check and its claim is refused too.

A claim records the holder's PID, host, boot id and process start time (from /proc): a claim whose process is
gone from this host, or whose PID now belongs to another process (a different start time, or a reboot), is
stale; the next claim of the same output removes it with a one-line warning. A claim of another host is never
judged: it stays until its process releases it, or a user deletes the claim file the message names.

Publishing (`publish`, which `outputs.atomic_path`, `schema.write` and the other writers use) renames the
finished temporary to the claimed name without replacing anything (renameat2 RENAME_NOREPLACE, else a hard
link or a check), unless `--force` was given and the output is still the one that existed when the claim was
taken. It also checks that the claim is still this process's. Paths nobody claimed (the files inside a claimed
run folder) are renamed over their old version as before.

Claims are released when the command ends (ev3dgs.cli.common.run), or at interpreter exit; a killed process's
claim is stale and cleared as above. A forked child never releases its parent's claims.

For tests, EV3DGS_TEST_PAUSE=POINT:FILE stops the process at POINT (`claimed`: right after its first claim;
`publish`: right before its first publish, the temporary output complete), writes its PID to FILE and waits
until FILE is deleted (at most 10 minutes): two writers can then race deterministically, and a process can be
killed mid-write at a known point.
"""
from __future__ import annotations

import contextlib
import errno as _errno
import json
import os
import socket
import stat
import sys
import time
import uuid
import warnings
from pathlib import Path

__all__ = ["Claim", "claim_output", "claim_run", "held_for", "release_all", "publish", "may_replace",
           "rename_noreplace", "pause", "RUN_LOCK", "PAUSE_ENV"]

RUN_LOCK = ".ev3dgs.lock"          # the claim of a folder written in place (a training run)
PAUSE_ENV = "EV3DGS_TEST_PAUSE"
_YOUNG_S = 10.0                     # an unreadable claim younger than this may be one being written (O_EXCL)

_held: dict[str, "Claim"] = {}     # claim file -> Claim, this process's
_paused: set[str] = set()
_atexit = False


def _errors():
    from .outputs import OutputError, os_error_message

    return OutputError, os_error_message


# ------------------------------------------------------------------------------------------------ identity

def _host() -> str:
    return socket.gethostname()


def _boot_id() -> str | None:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip() or None
    except OSError:
        return None


def _start_ticks(pid: int) -> int | None:
    """The process's start time in clock ticks since boot (/proc/PID/stat field 22), or None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return int(stat.rsplit(")", 1)[1].split()[19])
    except (OSError, ValueError, IndexError):
        return None


def _identity() -> dict:
    pid = os.getpid()
    argv0 = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else ""
    command = " ".join([argv0] + sys.argv[1:2]) if argv0.startswith("ev3dgs") else ""  # ev3dgs train
    return {"pid": pid, "host": _host(), "boot": _boot_id(), "start": _start_ticks(pid),
            "since": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()), "command": command[:120],
            "token": uuid.uuid4().hex}


def _parse(raw: bytes) -> dict | None:
    try:
        info = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        return None
    return info if isinstance(info, dict) and isinstance(info.get("pid"), int) else None


def _alive(info: dict | None, file: Path) -> bool:
    """Whether the claim's process may still be writing."""
    from .outputs import _pid_alive

    if info is None:  # unreadable: one being created with O_EXCL, else garbage
        try:
            return time.time() - file.stat().st_mtime < _YOUNG_S
        except OSError:
            return False
    if info.get("host") != _host():
        return True  # another machine's process: cannot be judged from here
    boot = _boot_id()
    if boot and info.get("boot") and info["boot"] != boot:
        return False  # made before a reboot
    pid = info["pid"]
    if pid == os.getpid():  # this process holds it, or it is an earlier process's under a reused PID
        return info.get("token") in {c.info["token"] for c in _held.values()}
    if not _pid_alive(pid):
        return False
    start, now = info.get("start"), _start_ticks(pid)
    return not (start is not None and now is not None and start != now)  # a reused PID


def _who(info: dict | None) -> str:
    if info is None:
        return "a claim being written"
    cmd = info.get("command")
    return f"pid {info.get('pid')} on host {info.get('host')}, since {info.get('since')}" + (
        f": {cmd}" if cmd else "")


# ------------------------------------------------------------------------------------------------ the claim

def _ident(path: Path):
    try:
        st = os.lstat(path)
    except OSError:
        return None
    if stat.S_ISDIR(st.st_mode):   # a folder's change time moves with its entries (the writable-folder probe)
        return (st.st_dev, st.st_ino)
    return (st.st_dev, st.st_ino, st.st_ctime_ns)  # ctime: a freed inode number can be reused at once


def _is_empty_dir(path: Path) -> bool:
    try:
        with os.scandir(path) as it:
            return next(it, None) is None
    except OSError:
        return False


class Claim:
    """This process's claim of `target` (see the module doc)."""

    def __init__(self, target: Path, file: Path, info: dict, force: bool, option: str, shown: str,
                 created: list[Path]):
        self.target, self.file, self.info, self.force = target, file, info, force
        self.option, self.shown = option, shown      # for messages: the option and the path as the user gave it
        self.seen = _ident(target)       # the output that existed when claimed (replaced only with force)
        self.ours = False                # seen is what this process published
        self.created = created           # folders made for the claim, removed again if left empty

    def owned(self) -> bool:
        try:
            info = _parse(self.file.read_bytes())
        except OSError:
            return False
        return info is not None and info.get("token") == self.info["token"]

    def may_replace(self, path: Path | None = None) -> bool:
        """True when the output may be replaced: --force (or an empty folder) and still the one seen at claim time."""
        path = self.target if path is None else path
        return _ident(path) == self.seen and (self.force or self.ours or _is_empty_dir(path))

    def check(self) -> None:
        OutputError, _ = _errors()
        if not self.owned():
            raise OutputError(f"{self.option} {self.shown}: the claim on it ({self.file}) was taken by another "
                              "process while this one was writing; nothing was written", _errno.EBUSY)

    def publish(self, tmp: Path, final: Path) -> None:
        OutputError, os_error_message = _errors()
        self.check()
        try:
            if self.may_replace(final):
                os.replace(tmp, final)
            else:
                rename_noreplace(tmp, final)
        except FileExistsError:
            raise OutputError(f"{self.option} {self.shown} appeared while this command was writing it (not by an "
                              "ev3dgs process that claimed it); it was not replaced", _errno.EEXIST) from None
        except OSError as e:
            if e.errno in (_errno.ENOTEMPTY, _errno.EEXIST):
                raise OutputError(f"{self.option} {self.shown} appeared while this command was writing it; it was "
                                  "not replaced", _errno.EEXIST) from None
            raise OutputError(f"cannot write {os_error_message(e, final)}", e.errno) from None
        self.seen, self.ours = _ident(final), True

    def release(self) -> None:
        if self.info["pid"] != os.getpid():
            return  # a forked child: the claim is its parent's
        _held.pop(str(self.file), None)
        if self.owned():
            with contextlib.suppress(OSError):
                os.unlink(self.file)
        for d in self.created:  # innermost first
            try:
                os.rmdir(d)
            except OSError:
                break


def _create(file: Path, info: dict) -> bool:
    """Create `file` with `info`, atomically with its content; False if it exists."""
    data = (json.dumps(info) + "\n").encode()
    tmp = file.with_name(f"{file.name}.new-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        try:
            os.link(tmp, file)
            return True
        except FileExistsError:
            return False
        except OSError as e:
            if e.errno not in (_errno.EPERM, _errno.ENOTSUP, _errno.EOPNOTSUPP, _errno.EXDEV, _errno.EMLINK,
                               _errno.ENOSYS):
                raise
        try:  # a file system without hard links
            fd = os.open(file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        return True
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def _break(file: Path, stale: bytes) -> None:
    """Remove the stale claim `file` whose bytes were `stale`, never a fresh claim made meanwhile."""
    aside = file.with_name(f"{file.name}.stale-{os.getpid()}")
    try:
        os.rename(file, aside)
    except FileNotFoundError:
        return  # another process removed it first
    try:
        if aside.read_bytes() != stale:  # a fresh claim took its place meanwhile: put it back
            with contextlib.suppress(FileExistsError):
                os.link(aside, file)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(aside)


def _make_dirs(folder: Path) -> list[Path]:
    """mkdir -p; returns the folders created, innermost first."""
    made = []
    p = folder
    while not p.exists() and p.parent != p:
        made.append(p)
        p = p.parent
    for d in reversed(made):
        try:
            d.mkdir()
        except FileExistsError:
            pass
    return made


def _take(target: Path, file: Path, shown: str, option: str, force: bool, created: list[Path]) -> Claim:
    OutputError, os_error_message = _errors()
    key = str(file)
    if key in _held and _held[key].info["pid"] == os.getpid():
        return _held[key]  # claimed already by this command
    info = _identity()
    for _ in range(50):
        try:
            if _create(file, info):
                break
            raw = file.read_bytes()
        except FileNotFoundError:
            continue
        except OSError as e:
            raise OutputError(f"cannot claim {option} {shown}: {os_error_message(e, file).split(': ', 1)[-1]}",
                              e.errno) from None
        other = _parse(raw)
        if _alive(other, file):
            hint = ("" if other is None or other.get("host") == _host() else
                    f"; if it is not running any more, delete {file}")
            raise OutputError(f"{option} {shown} is being written by another ev3dgs process ({_who(other)}){hint}; "
                              f"wait for it to finish or choose another {option}", _errno.EBUSY)
        _break(file, raw)
        warnings.warn(f"{option} {shown}: removed the stale claim of a process that is not running any more "
                      f"({_who(other)})", stacklevel=3)
    else:
        raise OutputError(f"cannot claim {option} {shown}: its claim file {file} keeps changing", _errno.EBUSY)
    claim = Claim(target, file, info, force, option, shown, created)
    _held[key] = claim
    global _atexit
    if not _atexit:
        import atexit

        atexit.register(release_all)
        _atexit = True
    pause("claimed")
    return claim


def claim_output(path: str | os.PathLike, *, force: bool = False, option: str = "--out",
                 folder: bool = False) -> Claim:
    """Claim the file (or, with `folder`, the folder built under a temporary name) `path` for this process:
    first the usual checks (outputs.check_output_file / check_output_dir: writable, a file or a folder where
    one is wanted, refused if it exists and not force), then the claim file `.NAME.claim` beside it, then the
    existence check again under the claim. OutputError (one line) when another process holds it."""
    from .outputs import (OutputError, check_output_dir, check_output_file, os_error_message, refuse_existing,
                          remove_stale_temps)

    shown = str(path)
    target = Path(os.path.abspath(path))
    if folder:
        check_output_dir(path, force=force, option=option)
    else:
        check_output_file(path, make_parents=True, force=force, option=option)
    try:
        created = _make_dirs(target.parent)
    except OSError as e:
        raise OutputError(f"cannot create the output folder {os_error_message(e, target.parent)}", e.errno) from None
    claim = _take(target, target.with_name(f".{target.name}.claim"), shown, option, force, created)
    try:
        refuse_existing(path, force, option)  # finished by another process between the check and the claim
    except BaseException:
        claim.release()
        raise
    remove_stale_temps(target.parent, target.name)  # what a killed writer of this output left (kill -9 too)
    return claim


def claim_run(folder: str | os.PathLike, *, option: str = "--out") -> Claim:
    """Claim a folder written in place (a training run: train and eval write into it) with a lock file inside
    it; the folder is created if missing (and removed again on release if the command leaves it empty)."""
    from .outputs import OutputError, check_output_dir, os_error_message

    shown = str(folder)
    target = Path(os.path.abspath(folder))
    check_output_dir(folder, option=option)
    try:
        created = _make_dirs(target)
    except OSError as e:
        raise OutputError(f"cannot create {option} {os_error_message(e, target)}", e.errno) from None
    return _take(target, target / RUN_LOCK, shown, option, True, created)


def held_for(path: str | os.PathLike) -> Claim | None:
    """This process's claim of exactly `path`, or None."""
    target = str(Path(os.path.abspath(path)))
    pid = os.getpid()
    for c in _held.values():
        if c.info["pid"] == pid and str(c.target) == target and c.file.name != RUN_LOCK:
            return c
    return None


def release_all() -> None:
    """Release every claim this process holds (the end of a command)."""
    for c in list(_held.values()):
        c.release()


# ------------------------------------------------------------------------------------------------ publishing

def rename_noreplace(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Rename `src` to `dst`, failing with FileExistsError when `dst` exists (a file or any folder):
    renameat2(RENAME_NOREPLACE) where the kernel and file system have it, else a hard link and unlink for
    files, and a check and rename for folders (rename never replaces a non-empty folder)."""
    src, dst = os.fspath(src), os.fspath(dst)
    fn = _renameat2()
    if fn is not None:
        import ctypes

        if fn(-100, os.fsencode(src), -100, os.fsencode(dst), 1) == 0:  # AT_FDCWD, RENAME_NOREPLACE
            return
        e = ctypes.get_errno()
        if e not in (_errno.EINVAL, _errno.ENOSYS, _errno.ENOTSUP, _errno.EOPNOTSUPP):
            raise OSError(e, os.strerror(e), src, None, dst)
    if os.path.isdir(src) and not os.path.islink(src):
        if os.path.lexists(dst):
            raise FileExistsError(_errno.EEXIST, os.strerror(_errno.EEXIST), dst)
        os.rename(src, dst)
        return
    try:
        os.link(src, dst)
    except FileExistsError:
        raise
    except OSError as e:
        if e.errno not in (_errno.EPERM, _errno.ENOTSUP, _errno.EOPNOTSUPP, _errno.EMLINK, _errno.ENOSYS):
            raise
        if os.path.lexists(dst):
            raise FileExistsError(_errno.EEXIST, os.strerror(_errno.EEXIST), dst) from None
        os.rename(src, dst)
        return
    os.unlink(src)


_RENAMEAT2 = []


def _renameat2():
    if not _RENAMEAT2:
        fn = None
        if sys.platform.startswith("linux"):
            try:
                import ctypes

                fn = ctypes.CDLL(None, use_errno=True).renameat2
                fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
                fn.restype = ctypes.c_int
            except (OSError, AttributeError):
                fn = None
        _RENAMEAT2.append(fn)
    return _RENAMEAT2[0]


def may_replace(path: str | os.PathLike) -> bool:
    """Whether a writer may replace what is at `path` now: yes where no claim of this process covers it (the
    caller's own checks apply), else as Claim.may_replace."""
    c = held_for(path)
    return True if c is None else c.may_replace(Path(os.path.abspath(path)))


def publish(tmp: str | os.PathLike, final: str | os.PathLike) -> None:
    """Give the finished temporary `tmp` its final name: under a claim without replacing anything unexpected
    (Claim.publish), else os.replace as before."""
    pause("publish")
    c = held_for(final)
    if c is None:
        os.replace(tmp, final)
    else:
        c.publish(Path(tmp), Path(os.path.abspath(final)))


def pause(point: str) -> None:
    """The EV3DGS_TEST_PAUSE hook (see the module doc)."""
    spec = os.environ.get(PAUSE_ENV, "")
    want, _, file = spec.partition(":")
    if want != point or not file or point in _paused:
        return
    _paused.add(point)
    with open(file, "w") as f:
        f.write(str(os.getpid()))
    deadline = time.monotonic() + 600
    while os.path.exists(file) and time.monotonic() < deadline:
        time.sleep(0.02)
