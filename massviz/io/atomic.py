"""Atomic file output: write to a temporary file beside the target, then rename it into place.

A reader never sees a half-written file, and an interrupted run leaves the previous file (if any) untouched.

What the user's path names is never replaced by something else (:func:`output_target`): a symlink is written
*through* (the file it points to is replaced, the link stays), a character or block device, a FIFO or a socket is
refused (one line; massviz writes whole files, never streams into devices or pipes).
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from massviz.errors import MassvizError
from massviz.signals import deferred

_KINDS = {stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device", stat.S_IFIFO: "a FIFO (named pipe)",
          stat.S_IFSOCK: "a socket"}


def output_target(path: str | Path, folder: bool = False) -> Path:
    """The path massviz really writes for the output ``path``: ``path`` itself, or for a symlink the file (or
    folder) it points to — written through, the link is kept. A device, FIFO or socket (also behind a link), or
    a link that cannot be resolved (a loop), is a ``MassvizError`` naming ``path``: it is never replaced."""
    path = Path(path)
    target = path
    if path.is_symlink():
        try:
            target = Path(os.path.realpath(path, strict=False))
            os.stat(path)  # a loop raises here
        except FileNotFoundError:
            pass  # a dangling link: the file it names is created
        except OSError as err:
            raise MassvizError(f"cannot resolve the symlink ({err.strerror or err})", path) from None
    try:
        mode = os.stat(target).st_mode
    except OSError:  # missing, or a parent that is not a folder: the callers' checks say which
        return target
    kind = _KINDS.get(stat.S_IFMT(mode))
    if kind is not None:
        via = f" (through the symlink to {target})" if target != path else ""
        raise MassvizError(f"is {kind}{via}; massviz writes whole {'folders' if folder else 'files'} only and "
                           "never replaces a device, FIFO or socket — give a file path", path)
    return target


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder (same suffix); on success rename it to ``path``.

    Write the whole file to the yielded path inside the ``with`` block. If the block raises, the temporary file is
    removed and ``path`` is left as it was. The new file gets the usual permissions (0666 minus the umask), not
    ``mkstemp``'s private 0600. A missing parent folder is a ``MassvizError``. A symlink is written through and a
    device/FIFO/socket refused (:func:`output_target`).
    """
    path = output_target(path)
    if path.is_dir():
        raise MassvizError("is a directory; a file path is needed", path)
    if not path.parent.is_dir():
        raise MassvizError(f"cannot write: folder {path.parent} does not exist", path)
    tmp = None
    try:
        with deferred():  # a signal now would leave the new temporary file behind
            sweep_stale(path.parent)
            fd, tmp = tempfile.mkstemp(prefix=_prefix(), suffix=f".tmp{_suffix(path)}", dir=path.parent)
            os.close(fd)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
        yield Path(tmp)
        os.replace(tmp, path)
    except OSError as err:
        _remove(tmp)
        raise _naming(err, path, tmp) from None
    except BaseException:
        _remove(tmp)
        raise


def _prefix() -> str:
    """The start of a temporary's name: hidden, short (``.mv-PID-`` and a few random characters: it fits wherever the
    output's own name fits, even a name of 255 bytes) and carrying this process's id (a temporary of a process that
    is gone, killed before it could remove it, is found by :func:`sweep_stale`)."""
    return f".mv-{os.getpid()}-"


#: the longest suffix a temporary keeps from its output's name (writers choose the format by it: ``.png``, ``.rrd``)
_MAX_SUFFIX = 16


def _suffix(path: Path) -> str:
    """The output's suffix (``.csv``), kept in the temporary's name when short; a long one is dropped."""
    return path.suffix if len(path.suffix.encode()) <= _MAX_SUFFIX else ""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process: alive
        return True
    return True


#: the name of a massviz temporary: ``.mv-PID-RANDOM`` then ``.tmp`` (and the output's suffix), ``.part`` or ``.old``
_TEMPORARY = re.compile(r"\.mv-(\d+)-[^/]*\.(tmp[^/]*|part|old)$")


def sweep_stale(folder: str | Path) -> None:
    """Remove the temporaries in ``folder`` that a massviz process left when it was killed (SIGKILL, a power cut):
    hidden ``.mv-PID-*`` files and folders ending ``.tmp*``, ``.part`` or ``.old`` whose process no longer runs.
    Repeated kills leave at most one run's temporaries, never an accumulation."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for entry in entries:
        m = _TEMPORARY.match(entry.name)
        if m is None or int(m.group(1)) == os.getpid() or _alive(int(m.group(1))):
            continue
        with deferred():
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)


def _remove(tmp) -> None:
    """Remove the temporary file or folder ``tmp`` (None: not made yet) whole, a signal held until it is gone."""
    if tmp is None:
        return
    with deferred():
        if os.path.isdir(tmp) and not os.path.islink(tmp):
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            Path(tmp).unlink(missing_ok=True)


def check_room(tmp: str | Path, nbytes: int = 1 << 16) -> None:
    """Write ``nbytes`` into the (empty) temporary file ``tmp`` and truncate it again: ``OSError`` when the disk is
    full or a file-size limit is below that. For writers that cannot report such a failure themselves (Rerun's
    file sink blocks for ever when its very first write fails)."""
    with open(tmp, "r+b") as fh:
        fh.write(bytes(nbytes))
        fh.flush()
        os.fsync(fh.fileno())
        fh.truncate(0)


def _naming(err: OSError, path: Path, tmp) -> BaseException:
    """An OS error met while writing the temporary ``tmp`` of ``path`` (a full disk: often without a file name, or
    naming the hidden temporary): one ``MassvizError`` naming ``path``. Errors about other files pass unchanged."""
    name = None if err.filename is None else str(err.filename)
    making = tmp is None and name is not None and Path(name).name.startswith(".mv-")  # making the temporary
    if name is None or making or (tmp is not None and name.startswith(str(tmp))):
        return MassvizError(f"cannot write ({err.strerror or err})", path)
    return err


@contextmanager
def atomic_dir(path: str | Path, keep_others: tuple[str, ...] | None = None) -> Iterator[Path]:
    """Yield a new temporary folder beside ``path``; on success it replaces ``path`` (an existing folder is moved
    aside, the new one renamed into place, then the old one removed). If the block raises, the temporary folder is
    removed and ``path`` is left as it was. The folder gets the usual permissions (0777 minus the umask). A symlink
    to a folder is written through (the link is kept); ``path`` naming a file, device or FIFO is refused.

    ``keep_others``: the patterns of what the command writes there (as :func:`check_replaceable`'s ``owned``); every
    other entry of the existing folder is kept (hard-linked into the new folder, which is then swapped with the old
    one in one step where Linux can: a kill at any moment leaves the old folder or the new one whole, each with
    them). Writers of the same ``path`` swap one at a time (a lock on its parent folder, held for the swap only): the
    folder ends as one writer's whole output."""
    path = output_target(path, folder=True)
    if path.exists() and not path.is_dir():
        raise MassvizError("exists and is not a folder", path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = None
    try:
        with deferred():  # a signal now would leave the new temporary folder behind
            sweep_stale(path.parent)
            tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=_prefix(), suffix=".part"))
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o777 & ~umask)
        yield tmp
        with deferred(), _folder_lock(path.parent):  # the swap runs to its end: the old or the new folder is in place
            if keep_others is not None and path.is_dir():
                _link_others(path, tmp, keep_others)
            # the user's files kept from the old folder: swapped in one step, so a kill never leaves them only in
            # a temporary (elsewhere two renames, each a commit a signal waits for)
            if keep_others is not None and path.exists() and _exchange(tmp, path):
                shutil.rmtree(tmp, ignore_errors=True)
            elif path.exists():
                old = Path(tempfile.mkdtemp(dir=path.parent, prefix=_prefix(), suffix=".old"))
                os.replace(path, old / path.name)
                os.replace(tmp, path)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
    except OSError as err:
        _remove(tmp)
        raise _naming(err, path, tmp) from None
    except MassvizError as err:  # name the file the user will look for, not the hidden one
        _remove(tmp)
        raise _renamed(err, tmp, path) from None
    except BaseException:
        _remove(tmp)
        raise


def _renamed(err: MassvizError, tmp, path: Path) -> MassvizError:
    """``err``, naming ``path``'s file instead when it names one inside the temporary folder ``tmp``."""
    if tmp is None or err.path is None or not err.path.startswith(str(tmp)):
        return err
    message = str(err)[len(err.path) + 2:]
    return MassvizError(message, path / Path(err.path).relative_to(tmp))


def _exchange(a: Path, b: Path) -> bool:
    """Swap the folders ``a`` and ``b`` in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the system
    or file system cannot (the caller then renames in two steps)."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


@contextmanager
def _folder_lock(folder: Path) -> Iterator[None]:
    """An exclusive lock (``flock``) on ``folder`` while the block runs, where its file system has locks: the swaps
    of writers of one output beside each other happen one after another."""
    import fcntl

    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        with contextlib.suppress(OSError):  # a file system without locks: the renames alone
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _link_others(old: Path, new: Path, owned: tuple[str, ...]) -> None:
    """Hard-link (copy where a link is refused) every entry of ``old`` that is not ``owned`` into ``new`` at the
    same place; folders that are owned are entered, others linked whole (links are linked as links)."""
    for folder, dirs, files in os.walk(old):
        rel_folder = Path(folder).relative_to(old)
        for name in list(dirs) + files:
            src, rel = Path(folder) / name, (rel_folder / name).as_posix()
            if _own(rel, owned) and name in dirs and not src.is_symlink():
                continue  # entered by the walk
            if name in dirs:
                dirs.remove(name)
            if _own(rel, owned):
                continue
            dst = new / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            if src.is_dir() and not src.is_symlink():
                shutil.copytree(src, dst, symlinks=True, copy_function=_link_or_copy, dirs_exist_ok=True)
            else:
                _link_or_copy(src, dst)


def _link_or_copy(src, dst) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


@contextmanager
def staged_files(folder: str | Path) -> Iterator[Path]:
    """Yield a hidden temporary folder inside ``folder`` (created if missing); on success every file written into
    it is moved into ``folder`` (replacing files of the same name; others in ``folder`` are kept). If the block
    raises (a full disk, a signal), the temporary folder is removed, and ``folder`` too when this call created it:
    a command writing several files into the user's folder leaves all of them or none."""
    folder = Path(folder)
    created = not folder.exists()
    stage = None
    try:
        with deferred():  # a signal now would leave the folder or the stage behind
            folder.mkdir(parents=True, exist_ok=True)
            sweep_stale(folder)
            stage = Path(tempfile.mkdtemp(dir=folder, prefix=_prefix(), suffix=".part"))
        yield stage
        with deferred():  # every file moves in, or (a failure) none: a signal waits for the end of the moves
            for item in sorted(stage.iterdir()):
                os.replace(item, folder / item.name)
            stage.rmdir()
    except MassvizError as err:  # name the file the user will look for, not the hidden one
        _remove(stage)
        if created:
            _remove(folder)
        raise _renamed(err, stage, folder) from None
    except BaseException:
        _remove(stage)
        if created:
            _remove(folder)
        raise


@contextmanager
def native_stderr(keep: int = 4096) -> Iterator[list[str]]:
    """Capture what native code (C libraries: Open3D's RPly, codecs) writes to file descriptor 2 inside the block:
    yields a list that holds, after the block, the first lines written (at most ``keep`` bytes; the rest is read
    and dropped, so the writer never blocks). Python's own ``sys.stderr`` is flushed first and is unaffected."""
    import sys
    import threading

    lines: list[str] = []
    try:
        sys.stderr.flush()
    except Exception:  # noqa: BLE001 - a closed or odd stderr: nothing to flush
        pass
    read_fd, write_fd = os.pipe()
    saved = os.dup(2)
    chunks: list[bytes] = []

    def drain():
        kept = 0
        while True:
            data = os.read(read_fd, 65536)
            if not data:
                return
            if kept < keep:
                chunks.append(data[:keep - kept])
                kept += len(chunks[-1])

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    os.dup2(write_fd, 2)
    os.close(write_fd)
    try:
        yield lines
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        reader.join(timeout=10)
        os.close(read_fd)
        lines.extend(line for line in b"".join(chunks).decode("utf-8", "replace").splitlines() if line.strip())


# ------------------------------------------------------------------------------------------- replacing own folders
def _own(rel: str, owned: tuple[str, ...]) -> bool:
    from pathlib import PurePosixPath

    parts = PurePosixPath(rel)
    return any(len(parts.parts) == len(PurePosixPath(p).parts) and parts.match(p) for p in owned)


def check_replaceable(path: str | Path, owned: tuple[str, ...], what: str, *, link_ok: bool = True) -> None:
    """Before a command replaces the folder ``path`` that it wrote before (``--force``, a sample regenerated): every
    entry under it is something massviz writes there (its path relative to ``path`` matches one of ``owned``, e.g.
    ``images`` and ``images/*.png``) and none is a symlink. Otherwise one ``MassvizError`` naming ``path`` and the
    entry, before anything is removed: a replacement never deletes what someone else put there, and never follows a
    link out of the folder. ``link_ok``: ``path`` itself may be a symlink (the user's own path, written through);
    False where massviz chose the name."""
    path = Path(path)
    if path.is_symlink() and not link_ok:
        raise MassvizError(f"is a symlink; massviz replaces only a {what} folder it wrote, never through a link "
                           "(remove the link)", path)
    root = output_target(path, folder=True)
    if not root.is_dir():
        return
    for folder, dirs, files in os.walk(root):
        for name in sorted(dirs) + sorted(files):
            full = Path(folder) / name
            rel = full.relative_to(root).as_posix()
            if full.is_symlink():
                raise MassvizError(f"holds the symlink {rel}; massviz never removes or writes through a link in an "
                                   f"output it replaces (remove the link, or choose another folder)", path)
            if not _own(rel, owned):
                raise MassvizError(f"holds {rel}, which is not part of a {what}; massviz replaces only what it wrote "
                                   "(move it away, or choose another folder)", path)


# ------------------------------------------------------------------------------------------- checking outputs first
def _probe_writable(folder: Path, path: Path) -> None:
    """Create and remove a temporary file in ``folder`` (the only sure test: modes, read-only mounts, quotas)."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as err:
        raise MassvizError(f"cannot write in folder {folder} ({err.strerror or err})", path) from None


def _check_name_lengths(path: Path) -> None:
    """Each part of ``path`` that does not exist yet fits the file system's limit on a name (255 bytes on Linux):
    a longer one is one line before any work, not a failure at the end."""
    ancestor = _existing_ancestor(path)
    try:
        limit = os.pathconf(ancestor, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    for part in [path, *path.parents]:
        if os.path.lexists(part):
            break
        size = len(os.fsencode(part.name))
        if size > limit:
            raise MassvizError(f"cannot write: the name {'of folder ' + str(part) + ' ' if part != path else ''}is "
                               f"{size} bytes (at most {limit} on this file system)", path)


def _existing_ancestor(path: Path) -> Path:
    for parent in path.parents:
        if parent.exists():
            return parent
    return Path(".")


def check_output_file(path: str | Path, option: str | None = None) -> Path:
    """Check, before any work starts, that ``path`` can be written as a file: it is not a folder, its folder
    exists, is a folder and is writable. ``MassvizError`` naming ``path`` otherwise. Nothing is left behind."""
    path = Path(path)
    needs = f"; {option} needs a file path" if option else ""
    output_target(path)
    _check_name_lengths(path)
    path = Path(os.path.realpath(path)) if path.is_symlink() else path
    if path.is_dir():
        raise MassvizError(f"is a directory{needs}", path)
    parent = path.parent
    if not parent.exists():
        raise MassvizError(f"cannot write: folder {parent} does not exist", path)
    if not parent.is_dir():
        raise MassvizError(f"cannot write: {parent} is not a folder", path)
    if path.exists() and not os.access(path, os.W_OK) and os.geteuid() != 0:
        raise MassvizError("cannot write: the file is read-only", path)
    _probe_writable(parent, path)
    return path


def check_output_dir(path: str | Path, option: str | None = None) -> Path:
    """Check, before any work starts, that ``path`` is a writable folder or can be created as one (every existing
    part of it is a folder, the nearest existing one writable). ``MassvizError`` naming ``path`` otherwise."""
    path = Path(path)
    needs = f"; {option} needs a folder" if option else ""
    output_target(path, folder=True)
    _check_name_lengths(path)
    if path.exists():
        if not path.is_dir():
            raise MassvizError(f"exists and is not a folder{needs}", path)
        _probe_writable(path, path)
        return path
    ancestor = _existing_ancestor(path)
    if not ancestor.is_dir():
        raise MassvizError(f"cannot create the folder: {ancestor} is not a folder", path)
    _probe_writable(ancestor, path)
    return path
