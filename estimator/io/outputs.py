"""Outputs written whole or not at all: a command's --out holds one complete run's files.

    with OutputFolder(args.out, ("estimate.mcap", "estimate.rrd", "summary.json")) as tmp:
        ...                                   # read, compute, write each name into tmp
    # here --out holds the new set; on an error, Ctrl-C or kill it still holds the previous one

    with OutputFile(args.out) as tmp:         # one file (simulate's LOG.mcap, metrics.json)
        simulate(..., tmp)

Entering checks the output before any work (one `PhysfuseError` line: not creatable, not
writable, a folder where a file goes, another run writing it) and takes a lock; leaving
without an exception puts the new outputs in place, leaving with one deletes them.

A folder of outputs (`OutputFolder`, estimate and calibrate):
  1. lock: `flock` on the --out folder itself (created empty when missing). A second run on
     the same folder is refused; the OS releases the lock when a run dies, even by SIGKILL.
     The lock is on the folder's inode, so it takes no file beside it and follows the swap.
  2. build: the run writes its files into a fresh folder beside --out on the same filesystem,
     `.NAME.tmp-<pid>-<random>`. Files of --out that are not the set's (a user's notes, the
     metrics.json of `physfuse evaluate`) are hard-linked into it just before the swap, so
     they are kept. --out must hold no subfolders (refused on entry), so that the swap never
     moves a folder holding someone else's work (or the shell's working folder).
  3. swap: one `renameat2(RENAME_EXCHANGE)` system call exchanges the two names: --out is the
     new folder, the temporary name holds the previous set, which is then deleted.
  Why this survives SIGKILL at any instant: before the swap --out is untouched (the previous
  complete set, or empty); the swap is a single atomic system call, so no instant shows a mix
  or no folder; after it --out is the new complete set. What a kill leaves is only the
  temporary folder, deleted by the next run on the same --out (under the lock, so never a live
  run's). Files and folders are fsynced before the swap, so a power loss is covered as far as
  the filesystem orders a rename after the data it names.
  Where the exchange is not available (not Linux, or a filesystem without it), the fallback
  renames --out aside to `.NAME.old-<pid>-<random>`, renames the new folder in and deletes
  the old one; a kill between the two renames leaves no --out and the previous set aside,
  which the next run renames back first: either set again, after that run starts.

A single file (`OutputFile`, simulate's LOG.mcap, evaluate's metrics.json, --config-out):
  written to `.NAME.tmp-<pid>-<random>` beside it, then `os.replace` (atomic) onto the name;
  the lock is `flock` on `.NAME.lock` beside it (removed afterwards).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import fcntl
import glob
import os
import shutil
import sys
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType

from estimator.errors import PhysfuseError


class OutputError(PhysfuseError):
    """An output cannot be written: the message names the option and the path."""


class OutputFolder:
    """A folder of outputs replaced as a whole (see the module docstring)."""

    def __init__(self, out: Path, names: Sequence[str], option: str = "--out") -> None:
        self.given = out  # as the user wrote it, for messages
        self.path = Path(os.path.realpath(out))  # a symlink's target is what gets swapped
        self.names = tuple(names)
        self.option = option
        self.tmp: Path | None = None
        self._lock: int | None = None
        self._created = False

    def _error(self, why: str) -> OutputError:
        return OutputError(f"{self.option} {self.given}: {why}")

    def __enter__(self) -> Path:
        path = self.path
        if path.exists() and not path.is_dir():
            raise self._error("is a file, expected a folder")
        if path.parent == path:
            raise self._error("is the filesystem's root; give a folder below it")
        _restore_aside(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._created = not path.exists()
            path.mkdir(exist_ok=True)  # to be locked
        except OSError as err:
            raise self._error(f"cannot create the folder ({err.strerror})") from err
        try:
            self._lock = _lock(path, directory=True, error=self._error)
            self._check()
            _remove_leftovers(path)
            try:
                self.tmp = _unique(path, "tmp")
                self.tmp.mkdir()
                shutil.copymode(path, self.tmp)  # the new --out gets the old one's permissions
            except OSError as err:
                raise self._error(f"cannot write in {path.parent} ({err.strerror})") from err
        except BaseException:
            self._abandon(failed=True)
            raise
        return self.tmp

    def _check(self) -> None:
        """What would make the run fail (or the swap unsafe) only at its end."""
        path = self.path
        if not os.access(path, os.W_OK | os.X_OK):
            raise self._error("is not writable")
        if path.stat().st_dev != path.parent.stat().st_dev:
            raise self._error("is a mount point; give a folder inside it")
        with contextlib.suppress(OSError):  # no current folder: nothing to protect
            if Path(os.getcwd()).is_relative_to(path):
                raise self._error(
                    "is the current folder, and --out is replaced as a whole when the run "
                    "completes: give a folder of its own"
                )
        with os.scandir(path) as entries:
            folders = sorted(e.name for e in entries if e.is_dir(follow_symlinks=False))
        for name in folders:
            if name in self.names:
                raise self._error(f"{path / name} is a folder, where this run writes a file")
        if folders:
            raise self._error(
                f"holds the folder {folders[0]!r}, and --out is replaced as a whole when the "
                f"run completes: give a folder without subfolders (e.g. {self.given}/run)"
            )

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        assert self.tmp is not None
        try:
            if error is None:
                self._commit(self.tmp)
            elif isinstance(error, OSError) and _inside(error.filename, self.tmp):
                name = Path(error.filename).relative_to(self.tmp)
                raise self._error(f"cannot write {name} ({error.strerror})") from error
        finally:
            self._abandon(failed=error is not None)

    def _commit(self, tmp: Path) -> None:
        missing = [n for n in self.names if not (tmp / n).is_file()]
        if missing:  # a bug, not a user error: never put a partial set in place
            raise RuntimeError(f"{self.given}: the run did not write {', '.join(missing)}")
        try:
            _carry_over(self.path, tmp, self.names)
            for name in self.names:  # the carried-over files are already on disk
                _fsync(tmp / name)
            _fsync(tmp)
            if not _exchange(tmp, self.path):
                _swap_by_renames(tmp, self.path)
            _fsync(self.path.parent)
        except OSError as err:
            raise self._error(f"cannot put the new outputs in place ({err.strerror})") from err

    def _abandon(self, failed: bool) -> None:
        """Delete the temporary folder (the unfinished set, or after the swap the previous
        one: either way not --out) and release the lock."""
        if self.tmp is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
        _restore_aside(self.path)  # only after a fallback swap interrupted between renames
        if failed and self._created and self._lock is not None:  # not another run's
            with contextlib.suppress(OSError):
                self.path.rmdir()  # made only to be locked, and still empty
        if self._lock is not None:
            os.close(self._lock)  # closing the descriptor releases the flock
            self._lock = None


class OutputFile:
    """One output file replaced atomically (see the module docstring).

    create_folder: make the file's folder when missing (else a missing folder is an error).
    keep_unchanged: leave the file as it is (and its time stamp) when the new one is the same.
    """

    def __init__(
        self,
        path: Path,
        option: str = "--out",
        *,
        create_folder: bool = True,
        keep_unchanged: bool = False,
    ) -> None:
        self.path = path
        self.option = option
        self.create_folder = create_folder
        self.keep_unchanged = keep_unchanged
        self.tmp: Path | None = None
        self._lock: tuple[int, Path] | None = None

    def _error(self, why: str) -> OutputError:
        return OutputError(f"{self.option} {self.path}: {why}")

    def __enter__(self) -> Path:
        path, folder = self.path, self.path.parent
        if path.is_dir():
            raise self._error("is a directory, expected a file path")
        if self.create_folder:
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as err:
                raise self._error(f"cannot create its folder ({err.strerror})") from err
        elif not folder.is_dir():
            raise self._error(f"folder {folder} does not exist")
        if path.exists() and not os.access(path, os.W_OK):
            raise self._error("is not writable")
        try:
            lock = folder / f".{path.name}.lock"
            self._lock = (_lock(lock, directory=False, error=self._error), lock)
            for leftover in glob.glob(glob.escape(str(folder / f".{path.name}.tmp-")) + "*"):
                with contextlib.suppress(OSError):
                    os.unlink(leftover)
            self.tmp = _unique(path, "tmp", path.suffix)  # the suffix: a type kept
            os.close(os.open(self.tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            if path.exists():
                shutil.copymode(path, self.tmp)
        except OSError as err:
            self._release()
            raise self._error(f"cannot write in {folder} ({err.strerror})") from err
        except BaseException:
            self._release()
            raise
        return self.tmp

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        assert self.tmp is not None
        try:
            if error is None:
                self._commit(self.tmp)
            elif isinstance(error, OSError) and error.filename == str(self.tmp):
                raise self._error(f"cannot write ({error.strerror})") from error
        finally:
            with contextlib.suppress(OSError):
                self.tmp.unlink()
            self._release()

    def _commit(self, tmp: Path) -> None:
        if self.keep_unchanged and _same_bytes(tmp, self.path):
            return
        try:
            _fsync(tmp)
            os.replace(tmp, self.path)
            _fsync(self.path.parent)
        except OSError as err:
            raise self._error(f"cannot write ({err.strerror})") from err

    def _release(self) -> None:
        if self._lock is not None:
            fd, lock_path = self._lock
            with contextlib.suppress(OSError):
                os.unlink(lock_path)  # while still holding it: see _lock
            os.close(fd)
            self._lock = None


def write_file(path: Path, text: str, option: str = "--out") -> None:
    """`path.write_text(text)`, atomically: the previous file or the new one, never a part."""
    with OutputFile(path, option) as tmp:
        tmp.write_text(text)


# -- locks ----------------------------------------------------------------------------------------
BUSY = "another physfuse run is writing it; wait for that run to end, or choose another path"


def _lock(path: Path, *, directory: bool, error: Callable[[str], OutputError]) -> int:
    """A descriptor holding `flock` on `path`: a folder itself, or a lock file (created).

    A folder's name moves to another folder at a swap, and a lock file's holder unlinks it
    on release; so once locked, check that the name still is what was opened, else retry."""
    flags = os.O_RDONLY | os.O_DIRECTORY if directory else os.O_RDWR | os.O_CREAT
    for _ in range(10):
        fd = os.open(path, flags, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise error(BUSY) from None
        with contextlib.suppress(OSError):
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                return fd
        os.close(fd)
    raise error(BUSY)


# -- the swap -------------------------------------------------------------------------------------
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _renameat2() -> Callable[..., int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):  # a C library older than glibc 2.28
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names `a` and `b` in one system call; False where the system cannot."""
    fn = _renameat2()
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False  # this filesystem (or kernel) has no exchange
    raise OSError(code, os.strerror(code), str(b))


def _swap_by_renames(tmp: Path, path: Path) -> None:
    """The fallback: `path` aside, `tmp` in; the aside folder is put back if the second
    rename fails, and by `_restore_aside` if the process dies between the two."""
    aside = _unique(path, "old")
    os.rename(path, aside)
    try:
        os.rename(tmp, path)
    except BaseException:
        os.rename(aside, path)
        raise
    shutil.rmtree(aside, ignore_errors=True)


def _restore_aside(path: Path) -> None:
    """No `path` but a previous set renamed aside by an interrupted fallback swap: put it back."""
    if os.path.lexists(path):
        return
    asides = glob.glob(glob.escape(str(path.parent / f".{path.name}.old-")) + "*")
    for aside in sorted(asides, key=os.path.getmtime, reverse=True):
        with contextlib.suppress(OSError):
            os.rename(aside, path)
            return


def _remove_leftovers(path: Path) -> None:
    """Temporary folders of killed runs on `path` (the caller holds its lock)."""
    for kind in ("tmp", "old"):
        for leftover in glob.glob(glob.escape(str(path.parent / f".{path.name}.{kind}-")) + "*"):
            shutil.rmtree(leftover, ignore_errors=True)


def _carry_over(old: Path, new: Path, names: Sequence[str]) -> None:
    """Entries of `old` that are not the set's, hard-linked into `new` (copied where a link
    is refused), so that the swap keeps them."""
    with os.scandir(old) as entries:
        for entry in entries:
            if entry.name in names:
                continue
            target = new / entry.name
            if entry.is_dir(follow_symlinks=False):  # made during the run: keep it too
                shutil.copytree(entry.path, target, symlinks=True, copy_function=_link_or_copy)
            else:
                _link_or_copy(entry.path, target)


def _link_or_copy(source: str, target: str | Path) -> None:
    try:
        os.link(source, target, follow_symlinks=False)
    except OSError:
        shutil.copy2(source, target, follow_symlinks=False)


# -- small helpers --------------------------------------------------------------------------------
def _unique(path: Path, kind: str, suffix: str = "") -> Path:
    """A new name beside `path` for this process: `.NAME.KIND-<pid>-<random>SUFFIX`."""
    return path.parent / f".{path.name}.{kind}-{os.getpid()}-{uuid.uuid4().hex[:8]}{suffix}"


def _fsync(path: Path) -> None:
    if path.is_symlink():
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _inside(filename: object, folder: Path) -> bool:
    return isinstance(filename, str) and Path(filename).is_relative_to(folder)


def _same_bytes(a: Path, b: Path) -> bool:
    try:
        return b.is_file() and a.read_bytes() == b.read_bytes()
    except OSError:
        return False
