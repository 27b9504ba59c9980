"""Outputs that are never half-written: files replaced atomically, and output
folders built in a staging folder and swapped into place.

The commands write their results through this one mechanism: ``bondgraph
loop``, ``estimate`` and ``sensitivity`` publish their output folders with
:class:`OutputFolder`; records (:meth:`bondgraph.data.records.Experiment.save`,
so ``simulate -o`` and ``simulate --noise``), ``simulate --stiffness``'s JSON
and the optimizer's checkpoints are atomic files. (The PNG folders of
``bondgraph plot`` and ``simulate --plot`` are still written in place.)

* :func:`write_text` / :func:`write_bytes` / :func:`replace_file` write a
  file next to its target under a temporary name and ``os.replace`` it into
  place: a reader (or a process killed in the middle) sees the old file or
  the new one, never a mix.
* :class:`OutputFolder` owns one output folder. It refuses a non-empty folder
  unless ``overwrite`` (checked when it is created, before any work), and
  :meth:`OutputFolder.publish` writes a *complete* version of the folder into
  a fresh staging folder beside it (``.NAME.staging-PID-N``) and swaps it
  with the target in one ``renameat2(RENAME_EXCHANGE)`` call (Linux), so the
  target is at every instant either the previous complete version or the new
  one. Where the exchange is not available it falls back to two renames (the
  target is then briefly absent, but still never mixed).
* A folder may be published many times: the residual-tracing loop publishes
  an *intermediate* report (``"finished": false``) after its initial fit and
  after every step, and the final one (``"finished": true``) at the end. An
  interrupted run therefore leaves the report of its last completed step in
  the output folder, and never a report whose files come from two versions.
* :meth:`OutputFolder.work_dir` is a persistent working folder beside the
  target (``.NAME.work``) for what must survive an interrupted run until it
  is published: the estimation checkpoint, the loop's running log.

Guarantees are against killed processes (SIGKILL, SIGINT); the files are
not fsync'ed, so a power loss may still lose the last version.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import itertools
import os
import shutil
import sys
from pathlib import Path
from typing import Callable, TypeVar

from bondgraph.errors import OutputError

T = TypeVar("T")

#: ``renameat2`` flag: exchange the two paths atomically (Linux >= 3.15)
RENAME_EXCHANGE = 2
_AT_FDCWD = -100
_counter = itertools.count()


def _renameat2():
    """libc's ``renameat2``, or None where it does not exist."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_RENAMEAT2 = _renameat2()


def exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths atomically; False where the system cannot
    (no ``renameat2``, or a file system without ``RENAME_EXCHANGE``).

    Raises
    ------
    OSError
        Any other failure of the system call.
    """
    if _RENAMEAT2 is None:
        return False
    rc = _RENAMEAT2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (22, 38, 95):            # EINVAL, ENOSYS, EOPNOTSUPP: not supported here
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


def _temporary(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{next(_counter)}")


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file + ``os.replace``).

    Raises
    ------
    OutputError
        The folder is missing or not writable (the path named).
    """
    path = Path(path)
    tmp = _temporary(path)
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}", path=path) from exc
    return path


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; see :func:`write_bytes`."""
    return write_bytes(path, text.encode("utf-8"))


def replace_file(path, write: Callable[[Path], object]) -> Path:
    """Let ``write(tmp)`` create a temporary file beside ``path``, then move it
    into place atomically (for writers that need a file name: ``np.savez``,
    ``savefig``). The temporary keeps the target's suffix.

    Raises
    ------
    OutputError
        The folder is missing or not writable.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}-{next(_counter)}{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"cannot write {path}: {exc.strerror or exc}", path=path) from exc
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def is_empty_dir(path: Path) -> bool:
    """True for an existing folder without entries."""
    return path.is_dir() and next(path.iterdir(), None) is None


class OutputFolder:
    """An output folder written only as complete versions (see the module).

    Parameters
    ----------
    path : path
        The folder.
    overwrite : bool
        Replace a non-empty folder (``--overwrite``); otherwise it is refused.
    option : str
        The option that named the folder, for messages (``"--out"``).

    Raises
    ------
    OutputError
        At construction, before any work: ``path`` is a file, a non-empty
        folder without ``overwrite``, or its parent cannot be created or
        written.
    """

    def __init__(self, path, *, overwrite: bool = False, option: str = "--out"):
        self.path = Path(path).absolute()
        self.overwrite = overwrite
        self.option = option
        self.published = 0
        self._check()
        self._remove_stale_staging()

    def _check(self) -> None:
        p = self.path
        if p.exists() and not p.is_dir():
            raise OutputError(f"{self.option} {p} is a file, not a folder", path=p)
        if p.is_dir() and not is_empty_dir(p) and not self.overwrite:
            raise OutputError(
                f"{self.option} {p} is not empty (it holds "
                f"{', '.join(sorted(q.name for q in p.iterdir())[:5])}"
                f"{', ...' if len(list(p.iterdir())) > 5 else ''})", path=p,
                hint=f"choose another {self.option}, or pass --overwrite to replace the folder "
                     f"(it is replaced as a whole, never mixed with the new files)")
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{self.option} {p}: cannot create the folder "
                              f"{p.parent}: {exc.strerror or exc}", path=p) from exc
        if not os.access(p.parent, os.W_OK | os.X_OK) or (
                p.is_dir() and not os.access(p, os.W_OK | os.X_OK)):
            raise OutputError(f"{self.option} {p}: the folder "
                              f"{p if p.is_dir() else p.parent} is not writable", path=p)

    def _remove_stale_staging(self) -> None:
        """Delete staging folders of earlier, killed runs (their process is gone)."""
        for q in self.path.parent.glob(f".{self.path.name}.staging-*"):
            pid = q.name.rsplit(".staging-", 1)[1].split("-")[0]
            if not pid.isdigit() or _alive(int(pid)):
                continue
            shutil.rmtree(q, ignore_errors=True)

    def work_dir(self, create: bool = True) -> Path:
        """The persistent working folder ``.NAME.work`` beside the target
        (created unless ``create`` is False); it survives an interrupted run.

        Raises
        ------
        OutputError
            The folder cannot be created (``--out`` named).
        """
        w = self.path.with_name(f".{self.path.name}.work")
        if not create:
            return w
        try:
            w.mkdir(exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{self.option} {self.path}: cannot create the working folder "
                              f"{w}: {exc.strerror or exc}", path=self.path) from exc
        return w

    def remove_work_dir(self) -> None:
        """Delete :meth:`work_dir` (after the final publish)."""
        shutil.rmtree(self.path.with_name(f".{self.path.name}.work"), ignore_errors=True)

    def publish(self, write: Callable[[Path], T]) -> T:
        """Write one complete version of the folder and swap it into place.

        Parameters
        ----------
        write : callable
            ``write(folder)`` writes every file of the version into the
            (empty) staging folder it is given; its return value is returned.

        Raises
        ------
        OutputError
            The target became a file or a non-empty folder of someone else
            in the meantime, or cannot be replaced.
        """
        staging = self.path.with_name(f".{self.path.name}.staging-{os.getpid()}-"
                                      f"{next(_counter)}")
        try:
            staging.mkdir()
            out = write(staging)
            self._swap_in(staging)
        except OSError as exc:
            raise OutputError(f"{self.option} {self.path}: {exc.strerror or exc}",
                              path=self.path) from exc
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        self.published += 1
        return out

    def _swap_in(self, staging: Path) -> None:
        """Move the complete ``staging`` folder to the target; the previous
        version ends up in ``staging`` (deleted by the caller)."""
        p = self.path
        if not self.published:
            self._check()      # the first version must not replace a folder of someone else
        if not p.exists():
            os.rename(staging, p)
            return
        if exchange(staging, p):
            return
        old = p.with_name(f".{p.name}.old-{os.getpid()}-{next(_counter)}")
        os.rename(p, old)
        os.rename(staging, p)
        shutil.rmtree(old, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether a process with this id exists."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
