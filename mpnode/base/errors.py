"""The one exception type for bad input.

Every reader in mpnode (trajectory files, model files, scene files, CLI values)
raises `InputError` so that callers catch one thing and users read one kind of
message: which file, which field, what is wrong and what was expected.
"""


class InputError(ValueError):
    """Malformed or inconsistent input.

    Parameters
    ----------
    source : str
        The file (or other origin, e.g. ``"--dt"``) the bad value came from.
    field : str
        The dataset, attribute, key or flag inside ``source`` that is wrong.
    problem : str
        What is wrong, e.g. ``"contains NaN at [3, 0, 1, 2]"``.
    expected : str, optional
        What a valid value looks like; doubles as the hint for the fix.
    """

    def __init__(self, source, field, problem, expected=None):
        self.source = str(source)
        self.field = str(field)
        self.problem = str(problem)
        self.expected = None if expected is None else str(expected)
        msg = f"{self.source}: {self.field}: {self.problem}"
        if self.expected:
            msg += f" (expected {self.expected})"
        super().__init__(msg)

    def __reduce__(self):
        # rebuilt from its four parts, so it survives the trip back from a worker process
        return type(self), (self.source, self.field, self.problem, self.expected)


class NumericalError(RuntimeError):
    """A computation produced NaN/inf or blew up (never written to disk)."""
