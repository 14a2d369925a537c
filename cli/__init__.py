"""The `mpnode` command line (installed as mpnode.cli): parses flags, calls the library, prints."""
