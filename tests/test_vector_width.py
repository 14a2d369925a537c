"""The vector width the kernels are compiled for: the `mpnode` command asks for the CPU's full
width (MPNODE_WIDE_VECTORS=1) before anything builds numba's code generator, its workers inherit
it, a host program gets numba's default, the user's NUMBA_CPU_FEATURES wins, and numba's
configuration is left as it was (mpnode.engine.codegen)."""
import os
import subprocess
import sys

import pytest
from numba.core.codegen import get_host_cpu_features

HOST = get_host_cpu_features()  # numba's view: what its own code generator would get
HAS_AVX512 = "+avx512f" in HOST.split(",")
needs_avx512 = pytest.mark.skipif(not HAS_AVX512, reason="no AVX-512 here: there is no wider vector to ask for")

# declaring the kernels builds numba's code generator (nothing is compiled)
FEATURES = """
from numba.core.registry import cpu_target
print(cpu_target.target_context.codegen().magic_tuple()[2])
"""
PROBE = "import numba\nfrom mpnode.engine import kernels\n" + FEATURES + "print(numba.config.CPU_FEATURES)\n"


def run(code, **env):
    clean = {k: v for k, v in os.environ.items()
             if k not in ("MPNODE_WIDE_VECTORS", "NUMBA_CPU_FEATURES", "NUMBA_ENABLE_AVX")}
    out = subprocess.run([sys.executable, "-c", code], env={**clean, **env}, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.splitlines()


@needs_avx512
def test_asking_lifts_llvms_256_bit_preference_and_restores_numbas_config():
    features, config = run(PROBE, MPNODE_WIDE_VECTORS="1")
    assert features == HOST + ",-prefer-256-bit"
    assert config == "None"


def test_without_asking_numba_keeps_its_default():
    features, config = run(PROBE)
    assert features == HOST
    assert config == "None"


@needs_avx512
def test_the_users_cpu_features_win():
    features, config = run(PROBE, MPNODE_WIDE_VECTORS="1", NUMBA_CPU_FEATURES=HOST)
    assert features == HOST
    assert config == HOST


@needs_avx512
def test_the_command_asks_before_numbas_generator_exists_and_its_workers_inherit_it():
    code = ("import os\nfrom numba.core.registry import cpu_target\nfrom cli.main import main\n"
            "main(['inspect', '--help'], standalone_mode=False)\n"
            "assert '_toplevel_target_context' not in vars(cpu_target), 'built before the command asked'\n"
            "from mpnode.engine import kernels\n" + FEATURES +
            "from mpnode.runs.executors import open_executor\n"
            "with open_executor(None, 1, one_thread=True) as farm:\n"
            "    print(farm.submit(os.getenv, 'MPNODE_WIDE_VECTORS').result())\n")
    assert run(code)[-2:] == [HOST + ",-prefer-256-bit", "1"]
    assert run(code, MPNODE_WIDE_VECTORS="0")[-2:] == [HOST, "0"]
