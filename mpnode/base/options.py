"""Options as dataclass fields that remember their older names, so that a configuration class is
the one place an option is declared: the command line's second flag names and the sweep file's
accepted keys both come from here."""
import dataclasses


def option(default, aliases=()):
    """A dataclass field with ``default`` that is also accepted under the names ``aliases``."""
    return dataclasses.field(default=default, metadata={"aliases": tuple(aliases)})


def aliases(cls, name):
    """The older names of the option ``name`` of the configuration class ``cls``."""
    return next(f.metadata.get("aliases", ()) for f in dataclasses.fields(cls) if f.name == name)


def option_names(cls):
    """{name or older name: option name} of every field of the configuration class ``cls``."""
    out = {}
    for f in dataclasses.fields(cls):
        out[f.name] = f.name
        out.update({alias: f.name for alias in f.metadata.get("aliases", ())})
    return out


def defaults(cls):
    """{option name: default} of the configuration class ``cls``."""
    return {f.name: f.default for f in dataclasses.fields(cls)}
