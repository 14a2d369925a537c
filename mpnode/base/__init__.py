"""What every layer shares: the error types, CSR graphs, atomic writes and the TOML and HDF5
reading helpers.

Owns: `errors` (InputError, NumericalError), `oserrors` (FileSystemError: the system's refusals
as sentences), `locks` (outputs claimed by a running command), `memory` (sizes checked before
allocating), `arguments` (the Python API's arguments checked), `graph` (Graph), `atomic` (files that are
written whole or not at all), `tomlfile`, `h5`.  May import: nothing else of mpnode (numpy
and the standard library; h5py inside functions).
"""
