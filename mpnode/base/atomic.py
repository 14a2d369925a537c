"""Files that behave like files: atomic, durable writes, and outputs that never destroy inputs.

A write goes to a temporary file in the target's folder, created with the mode a plain
``open(path, "w")`` would give (0666 less the umask, or the mode of the file it
replaces), flushed to disk, then renamed onto the target, and the folder is flushed too:
an interrupted run (Ctrl-C, kill, crash, power loss) leaves either the old file or the
complete new one, and "written" means on disk.  Files that must agree are written as a pair
(`atomic_paths`).  When the system refuses (a full disk, a read-only folder), the error is a
FileSystemError naming the file the user asked for (mpnode.base.oserrors).
"""
import contextlib
import os
import secrets
import stat

from .errors import InputError
from .oserrors import FileSystemError, as_os_error, file_error


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path next to ``path``; move it onto ``path`` durably on success.

    On any exception the temporary file is removed and ``path`` is untouched; an OSError
    (a full disk, a read-only folder) comes out as a FileSystemError naming ``path``.
    """
    with atomic_paths(path) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_paths(*paths):
    """Yield temporary paths next to each of ``paths``; on success move them onto ``paths``.

    Every file is written and flushed before the first is renamed, so files that must agree
    (a model and its checkpoint) stay a pair: a failure while writing leaves all the old ones.
    """
    temps = []
    try:
        for path in map(os.fspath, paths):
            temps.append((path, _new_temp(path)))
        yield [tmp for _, tmp in temps]
        for path, tmp in temps:
            _flush(path, tmp)
        for path, tmp in temps:
            os.replace(tmp, path)
        for folder in dict.fromkeys(os.path.dirname(os.path.abspath(p)) for p, _ in temps):
            _fsync(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except BaseException as e:
        for _, tmp in temps:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        e = as_os_error(e) or e
        if isinstance(e, OSError):
            path = _named(e, temps, paths)
            if isinstance(e, FileSystemError) and e.filename != path:  # a nested write named our temporary file
                e.filename = path
            raise file_error(e, path) from None
        raise


def _new_temp(path):
    """An empty temporary file beside ``path`` with the mode ``open(path, "w")`` would give it."""
    tmp = _beside(path, "tmp")
    mode = 0o666
    with contextlib.suppress(FileNotFoundError):
        mode = stat.S_IMODE(os.stat(path).st_mode)
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode))  # the umask applies to a new file
    return tmp


def _beside(path, suffix):
    folder, name = os.path.split(os.path.abspath(path))
    return os.path.join(folder, f".{name}.{secrets.token_hex(4)}.{suffix}")


def _flush(path, tmp):
    """The replaced file's mode, exactly, and the temporary file's contents on disk."""
    with contextlib.suppress(FileNotFoundError):
        mode = stat.S_IMODE(os.stat(path).st_mode)
        if mode != stat.S_IMODE(os.stat(tmp).st_mode):
            os.chmod(tmp, mode)
    _fsync(tmp, os.O_RDONLY)


def _named(error, temps, paths):
    """The user's file an OSError is about: the one whose temporary file it names, else the first."""
    name = getattr(error, "filename", None)
    for path, tmp in temps:
        if name in (path, tmp):
            return path
    return temps[-1][0] if temps else os.fspath(paths[0])


def _fsync(path, flags):
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def check_writable(path):
    """FileSystemError unless a file can be created beside ``path`` (a read-only disk or a
    folder without write permission is found before any work, not after it)."""
    probe = _beside(path, "probe")
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        os.unlink(probe)
    except OSError as e:
        raise file_error(e, path) from None


def check_outputs(outputs, inputs):
    """InputError unless every output can be written without touching an input.

    outputs : {flag: path} the command will write (its folder must exist; no two the same);
    inputs : paths the command reads.  The same file by any path (links, ../, symlinks)
    counts as the same.  Then FileSystemError unless each output's folder takes a new file.
    """
    def same(a, b):
        try:
            return os.path.samefile(a, b)
        except OSError:  # one of them does not exist (yet): compare where they would be
            return os.path.realpath(a) == os.path.realpath(b)

    for flag, out in outputs.items():
        folder = os.path.dirname(os.path.abspath(out))
        if not os.path.isdir(folder):
            raise InputError(flag, out, f"folder {folder} does not exist", "a path in an existing folder")
        for src in inputs:
            if same(out, src):
                raise InputError(flag, out, f"is the input file {src}; writing it would destroy the input",
                                 "a new file name for the output")
    written = list(outputs.items())
    for k, (flag, out) in enumerate(written):
        for other_flag, other in written[:k]:
            if same(out, other):
                raise InputError(flag, out, f"is also the file of {other_flag}; one would overwrite the other",
                                 "a different file name for each output")
    folders = {os.path.dirname(os.path.abspath(out)): out for out in outputs.values()}
    for out in folders.values():
        check_writable(out)
