"""The training log: one JSON object per epoch, beside the model file as ``MODEL.log.jsonl``.

Every line is written by one write() on an O_APPEND descriptor, so a run killed at any
moment (SIGKILL, power) leaves whole lines only.
"""
import contextlib
import json
import math
import os

import numpy as np

from mpnode.base.atomic import atomic_path
from mpnode.base.oserrors import file_error


def log_path(output):
    """The JSON-lines training log beside the model file ``output``."""
    return os.fspath(output) + ".log.jsonl"


class TrainLog:
    """Appends epoch records to the log of ``output`` (nothing when output is None)."""

    def __init__(self, output):
        self.path = None if output is None else log_path(output)
        self.fd = None

    def start(self, first_record=None, keep_epochs=None):
        """Open the log: a new one holding ``first_record``, or the old one cut after epoch ``keep_epochs``.

        Returns the records kept (resume) or [first_record].
        """
        if self.path is None:
            return [] if first_record is None else [first_record]
        if first_record is not None:
            with atomic_path(self.path) as tmp, open(tmp, "w") as f:
                f.write(_line(first_record))
            records = [first_record]
        else:
            records = truncate(self.path, keep_epochs)
        self.fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        return records

    def append(self, record):
        if self.fd is None:
            return
        data = _line(record).encode()
        try:
            written = os.write(self.fd, data)
            while written < len(data):  # not seen for regular files; finish rather than tear the line
                written += os.write(self.fd, data[written:])
        except OSError as e:  # a full disk: the caller stops the run
            raise file_error(e, self.path, "append to the training log") from None

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def remove(self):
        """Close and delete the log (a run that stopped before it saved anything leaves no log)."""
        self.close()
        if self.path is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)


def _line(record):
    return json.dumps({k: _jsonable(v) for k, v in record.items()}) + "\n"


def _jsonable(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, np.generic):
        return _jsonable(v.item())
    return v


def read_log(path):
    """The records of a training log (list of dicts), skipping a last line a crash could have cut.

    Lines are written whole, so a cut line should not occur; the reader still tolerates one
    (the last line, without its newline) rather than fail on it.
    """
    records = []
    with open(path) as f:
        for line in f:
            try:
                records.append(json.loads(line))
            except ValueError:
                if line.endswith("\n"):
                    raise
    return records


def truncate(path, epoch):
    """Keep the log lines of epochs <= ``epoch`` (a resumed run redoes the later ones); returns them."""
    kept, records = [], []
    try:
        with open(path) as f:
            for line in f:
                try:
                    r = json.loads(line)
                except ValueError:
                    continue  # a line cut by a kill
                if r.get("epoch", math.inf) <= epoch:
                    kept.append(line if line.endswith("\n") else line + "\n")
                    records.append(r)
    except FileNotFoundError:
        pass
    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.writelines(kept)
    return records
