"""Files that behave like files: atomic, durable writes, and outputs that never destroy inputs.

A write goes to a temporary file in the target's folder, created with the mode a plain
``open(path, "w")`` would give (0666 less the umask, or the mode of the file it
replaces), flushed to disk, then renamed onto the target, and the folder is flushed too:
an interrupted run (Ctrl-C, kill, crash, power loss) leaves either the old file or the
complete new one, and "written" means on disk.
"""
import contextlib
import os
import secrets
import stat

from .errors import InputError


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path next to ``path``; move it onto ``path`` durably on success.

    On any exception the temporary file is removed and ``path`` is untouched.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{secrets.token_hex(4)}.tmp")
    mode = 0o666
    with contextlib.suppress(FileNotFoundError):
        mode = stat.S_IMODE(os.stat(path).st_mode)
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode))  # the umask applies to a new file
    try:
        yield tmp
        if mode != 0o666:
            os.chmod(tmp, mode)  # the replaced file's mode, exactly
        _fsync(tmp, os.O_RDONLY)
        os.replace(tmp, path)
        _fsync(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _fsync(path, flags):
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def check_outputs(outputs, inputs):
    """InputError unless every output can be written without touching an input.

    outputs : {flag: path} the command will write (its folder must exist; no two the same);
    inputs : paths the command reads.  The same file by any path (links, ../, symlinks)
    counts as the same.
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
