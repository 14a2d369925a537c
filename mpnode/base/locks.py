"""Outputs claimed by a running command: a lock file beside each, so two runs never write one file.

``claim(path, command)`` holds ``path + ".lock"`` while its block runs: an exclusive
``flock`` on the lock file, which holds who claimed it (pid, host, command, start time) for
the message a second claimant gets -- an InputError naming that run.  The kernel drops a
flock when its process ends, however it ends, so the lock of a run that was killed is
simply taken over; a run that ends normally (or by Ctrl-C) removes its lock file.  Where
the filesystem does not support locks (ENOLCK), the output is written unclaimed.
"""
import contextlib
import errno
import fcntl
import json
import os
import socket
import time

from .errors import InputError
from .oserrors import file_error


def lock_path(path):
    """The lock file beside ``path`` (a file or a folder)."""
    return os.path.normpath(os.path.abspath(os.fspath(path))) + ".lock"


@contextlib.contextmanager
def claim(path, command, flag="--output"):
    """Hold the lock of ``path`` while the block runs (module docstring).

    command : what the holder is doing, for a second claimant's message (e.g. the command
    line);  flag : the option that named ``path`` (the InputError's source).
    """
    lock = lock_path(path)
    fd = _take(lock, path, command, flag)
    try:
        yield lock
    finally:
        if fd is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(lock)
            os.close(fd)


def _take(lock, path, command, flag):
    """The descriptor of ``lock``, locked and holding this run's details; None if unsupported."""
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as e:
            raise file_error(e, lock, "create the lock file") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise InputError(flag, path, f"is being written by another run ({holder}; lock file {lock})",
                             "to wait until that run ends, or another output name") from None
        except OSError as e:
            os.close(fd)
            if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP):
                return None
            raise file_error(e, lock, "lock") from None
        if _same_file(fd, lock):  # not a lock file its last holder removed while we waited for it
            break
        os.close(fd)
    details = {"pid": os.getpid(), "host": socket.gethostname(), "command": command,
               "started": time.strftime("%Y-%m-%d %H:%M:%S")}
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps(details).encode(), 0)
    return fd


def _same_file(fd, path):
    try:
        return os.fstat(fd).st_ino == os.stat(path).st_ino
    except FileNotFoundError:
        return False


def _holder(fd):
    """Who holds a lock, as a phrase."""
    try:
        d = json.loads(os.pread(fd, 4096, 0).decode())
        return f"pid {d['pid']} on {d['host']}, `{d['command']}`, started {d['started']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "a run that is just starting"
