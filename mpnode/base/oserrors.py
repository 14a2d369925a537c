"""Operating-system failures as sentences: which file, what the system refused, and the fix.

A full disk, a read-only folder, a missing permission or a file held by another program is
not bad input, but a user should read it the same way: one paragraph naming the file, what
mpnode was doing with it, why the system said no, what to do, and what is left on disk.
Writers raise `FileSystemError` (an OSError, so ``except OSError`` still catches it) with
the file the user named, not a temporary file beside it; `explain` words any OSError.
"""
import errno
import os
import re

#: errno -> what to do about it (the message's fix)
FIXES = {
    errno.ENOSPC: "the disk is full: free space on it, or write to another disk",
    errno.EDQUOT: "your disk quota is used up: free space, or write to another disk",
    errno.EROFS: "the filesystem is mounted read-only: write to a folder on a writable disk",
    errno.EACCES: "you lack the permission: choose a file or folder you may use, or change its permissions",
    errno.EPERM: "the system does not permit it: choose a file or folder you may use, or change its permissions",
    errno.ENOENT: "a folder on the way does not exist: create it, or correct the path",
    errno.ENOTDIR: "a part of the path is a file, not a folder: correct the path",
    errno.EISDIR: "it is a folder: give a file name",
    errno.EBUSY: "another program holds it: close that program, or use another name",
    errno.ETXTBSY: "another program holds it: close that program, or use another name",
    errno.EMFILE: "too many files are open: close other programs, or raise the limit (ulimit -n)",
    errno.ENFILE: "the system has too many files open: close other programs",
    errno.EIO: "the device reported an input/output error: check the disk (or the network filesystem)",
    errno.ENAMETOOLONG: "the name is too long for the filesystem: use a shorter path",
    errno.ENOMEM: "the system ran out of memory: close other programs, or ask for less",
    errno.ELOOP: "the path loops through symbolic links: correct the path",
}


#: errnos by which the system refuses to read a file that is there (a damaged file has none)
REFUSALS = (errno.EACCES, errno.EPERM, errno.EIO, errno.EMFILE, errno.ENFILE, errno.ENOMEM, errno.EBUSY)


def refused(error):
    """Whether ``error`` (an exception) is the system refusing access, not the file's contents."""
    return isinstance(error, OSError) and error.errno in REFUSALS


class FileSystemError(OSError):
    """The system refused an operation on a file the user named.

    errno, strerror : the system's answer;  filename : the file (the one the user named);
    doing : what mpnode was doing, e.g. "write" or "read";  left : what is left on disk
    and how to go on (a sentence, or None).
    """

    def __init__(self, code, strerror, filename, doing="write", left=None):
        super().__init__(code, strerror, filename)
        self.doing, self.left = doing, left

    def __str__(self):
        return explain(self)

    def __reduce__(self):
        # rebuilt from its parts, so it survives the trip back from a worker process
        return type(self), (self.errno, self.strerror, self.filename, self.doing, self.left)


def file_error(error, path, doing="write", left=None):
    """``error`` (any OSError) as a FileSystemError on ``path``; one already naming a file keeps it."""
    if isinstance(error, FileSystemError):
        if left is not None:
            error.left = left
        return error
    code = error.errno or _errno_in_text(str(error))
    strerror = os.strerror(code) if code else (error.strerror or str(error) or type(error).__name__)
    return FileSystemError(code, strerror, os.fspath(path), doing, left)


def as_os_error(error):
    """``error`` as an OSError: itself, or libhdf5's RuntimeError that names the system's errno
    (a write that failed when the file was closed, e.g. on a full disk); None for anything else."""
    if isinstance(error, OSError):
        return error
    code = _errno_in_text(str(error)) if isinstance(error, RuntimeError) else None
    return OSError(code, os.strerror(code)) if code else None


def _errno_in_text(text):
    """The errno some libraries (libhdf5) give only in their message ("errno = 28"), or None."""
    match = re.search(r"errno = (\d+)", text)
    return int(match.group(1)) if match else None


def explain(error):
    """One paragraph for any OSError: the file, what was done, the system's answer, the fix,
    and (a FileSystemError's) what is left on disk."""
    code = error.errno
    name = errno.errorcode.get(code, "")
    why = (os.strerror(code) if code else None) or error.strerror or str(error.args[0] if error.args else error)
    doing = getattr(error, "doing", None) or "use"
    where = f"{error.filename}: " if error.filename else ""
    fix = FIXES.get(code, "check the path and the filesystem")
    text = f"{where}cannot {doing}: {why}" + (f" [{name}]" if name else "") + f" ({fix})"
    left = getattr(error, "left", None)
    return text + (f". {left}" if left else "")
