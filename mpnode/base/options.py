"""Options as dataclass fields that remember their older names and their switches, so that a
configuration class is the one place an option is declared: the command line's flag names and
the sweep file's accepted keys both come from here."""
import dataclasses


def option(default, aliases=(), switches=None):
    """A dataclass field with ``default`` that is also accepted under the names ``aliases``, and
    set to ``value`` by each key of ``switches`` ({key: value}) given as true: a flag's form of
    one choice (``clip_global = true`` is ``clip_mode = "global"``)."""
    return dataclasses.field(default=default, metadata={"aliases": tuple(aliases), "switches": dict(switches or {})})


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


def switches(cls):
    """{key: (option name, value)} of the switches of every field of the configuration class ``cls``."""
    return {key: (f.name, value) for f in dataclasses.fields(cls) for key, value in f.metadata.get("switches",
                                                                                                   {}).items()}


def defaults(cls):
    """{option name: default} of the configuration class ``cls``."""
    return {f.name: f.default for f in dataclasses.fields(cls)}
