"""The vector width the kernels are compiled for: the `mpnode` command asks for the CPU's full
width (MPNODE_WIDE_VECTORS=1), a host program gets numba's default, the user's NUMBA_CPU_FEATURES
wins, and numba's configuration is left as it was (mpnode.engine.kernels)."""
import os
import subprocess
import sys

import llvmlite.binding as llvm
import pytest

HOST = llvm.get_host_cpu_features().flatten()
HAS_AVX512 = "+avx512f" in HOST.split(",")

# declaring the kernels builds numba's code generator (nothing is compiled)
PROBE = """
import numba
from numba.core.registry import cpu_target
from mpnode.engine import kernels
print(cpu_target.target_context.codegen().magic_tuple()[2])
print(numba.config.CPU_FEATURES)
"""


def run(code, **env):
    clean = {k: v for k, v in os.environ.items() if k not in ("MPNODE_WIDE_VECTORS", "NUMBA_CPU_FEATURES")}
    out = subprocess.run([sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True,
                         check=True, timeout=300)
    return out.stdout.splitlines()


@pytest.mark.skipif(not HAS_AVX512, reason="the CPU has no AVX-512: there is no wider vector to ask for")
def test_asking_lifts_llvms_256_bit_preference_and_restores_numbas_config():
    features, config = run(PROBE, MPNODE_WIDE_VECTORS="1")
    assert features == HOST + ",-prefer-256-bit"
    assert config == "None"


def test_without_asking_numba_keeps_its_default():
    features, config = run(PROBE)
    assert "prefer-256-bit" not in features
    assert config == "None"


def test_the_users_cpu_features_win():
    features, config = run(PROBE, MPNODE_WIDE_VECTORS="1", NUMBA_CPU_FEATURES=HOST)
    assert features == HOST
    assert config == HOST


def test_the_command_asks_for_its_own_process():
    code = ("import os\nfrom cli.main import main\nmain(['inspect', '--help'], standalone_mode=False)\n"
            "print(os.environ.get('MPNODE_WIDE_VECTORS'))")
    assert run(code)[-1] == "1"
    assert run(code, MPNODE_WIDE_VECTORS="0")[-1] == "0"
