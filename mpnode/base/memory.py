"""Sizes checked before allocating: what a command will need against what the machine has.

A request far beyond the machine (``-B 10**12``, ``--hidden 100000``) must be refused like
bad input, naming the option to change, before any work -- not end in a MemoryError after
minutes, or in the kernel's out-of-memory killer.  Estimates count the large arrays only;
what the machine has is Linux's MemAvailable (memory a new allocation can get without
swapping), else the free physical pages; where neither is known, nothing is refused.
"""
import os

from .errors import InputError


def available_bytes():
    """Bytes of memory a new allocation can get now, or None where the system does not say."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):
        return None


def check_memory(need, source, field, what, fix):
    """InputError(source, field, ...) when ``need`` bytes (for ``what``, a phrase) exceed what
    the machine has available; ``fix`` says which option to change."""
    have = available_bytes()
    if have is not None and need > have:
        raise InputError(source, field, f"{what} needs about {format_bytes(need)} of memory, but this machine "
                         f"has {format_bytes(have)} available", fix)


def format_bytes(n):
    """1234567 -> '1.23 MB' (powers of 1000, as disks and `free --si` count)."""
    units = ("B", "kB", "MB", "GB", "TB", "PB", "EB")
    k = 0
    while n >= 1000 and k < len(units) - 1:
        n, k = n / 1000, k + 1
    return f"{int(n)} B" if k == 0 else f"{n:.3g} {units[k]}"
