"""The `mpnode` command line (installed as cli): parses flags, calls the library, prints."""
