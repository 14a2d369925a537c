"""Reading a TOML file into a dict, with every way it can fail turned into one InputError."""
import os
import tomllib

from .errors import InputError


def load_toml(path, what):
    """The document in ``path``; ``what`` says what the file should be (e.g. "a TOML scene file"),
    for the message a user reads when it is missing, unreadable or not TOML."""
    source = os.fspath(path)
    try:
        with open(source, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise InputError(source, "file", "does not exist", what) from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(source, "TOML", str(e), f"{what}, valid TOML") from None
    except UnicodeDecodeError as e:
        raise InputError(source, "TOML", f"is not UTF-8 text ({e.reason} at byte {e.start})", f"{what}, valid TOML") from None
    except OSError as e:  # a folder, no permission, ...
        raise InputError(source, "file", f"cannot be read ({e.strerror or e})", f"{what}, readable") from None
