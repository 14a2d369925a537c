"""What every layer shares: the error types, CSR graphs, atomic writes and the TOML and HDF5
reading helpers.

Owns: `errors` (InputError, NumericalError), `graph` (Graph), `atomic` (files that are
written whole or not at all), `tomlfile`, `h5`.  May import: nothing else of mpnode (numpy
and the standard library; h5py inside functions).
"""
