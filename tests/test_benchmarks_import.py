"""benchmarks/ is a harness: every script there imports (so none refers to code that is gone), and
the paper suite's modules import each other without a cycle, each experiment only the shared modules."""
import ast
import subprocess
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
PAPER = BENCHMARKS / "paper"
#: the paper suite's modules every experiment may import (the run definitions, the paper's numbers, helpers)
SHARED = {"common", "runs_shared", "paper_numbers", "gene_grid"}
#: the study scripts kept in the tree
STUDIES = {"grid_inverse.py", "imperfect_data.py", "long_rollouts.py", "network_fit_error.py", "spread_ranking.py",
           "time_to_accuracy.py", "tta_torch.py", "mpc/figures.py", "mpc/pendulum_mpc.py", "mpc/plan_windows.py",
           "mpc/quadrotor_mpc.py", "mpc/torque_segments.py", "mpc/true_equations.py", "quadrotor/sizes_table.py",
           "quadrotor/swarm.py", "spring_chains.py"}

IMPORT_ALL = """
import importlib.util, sys, traceback
failed = []
for path in sys.argv[1:]:
    folder = path.rsplit("/", 1)[0]
    sys.path[:0] = [folder]  # as `python path` runs it: its folder first
    try:
        spec = importlib.util.spec_from_file_location("bench_" + str(len(failed)) + path.replace("/", "_")[:-3], path)
        spec.loader.exec_module(importlib.util.module_from_spec(spec))
    except BaseException:
        failed.append(path + "\\n" + traceback.format_exc(limit=-2))
    finally:
        sys.path.remove(folder)
print("\\n".join(failed))
"""


def scripts():
    return sorted(str(p) for p in BENCHMARKS.rglob("*.py") if "work" not in p.relative_to(BENCHMARKS).parts)


def test_every_benchmark_script_imports():
    files = scripts()
    assert len(files) > 20 and any(f.endswith("studies/tta_torch.py") for f in files)
    # the studies kept in the tree: those whose evidence is current (the others live in the history)
    studies = {f.split("benchmarks/studies/", 1)[1] for f in files if "benchmarks/studies/" in f}
    assert studies == STUDIES, f"benchmarks/studies changed: update STUDIES ({sorted(studies ^ STUDIES)})"
    # one fresh interpreter (the scripts set numba threads and matplotlib backends) importing them all
    out = subprocess.run([sys.executable, "-c", IMPORT_ALL, *files], capture_output=True, text=True, timeout=300,
                         cwd=BENCHMARKS.parent)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip() == "", "these scripts fail to import:\n" + out.stdout


def suite_imports():
    """module -> the paper suite's modules it imports (anywhere in the file, at any depth)."""
    local = {p.stem for p in PAPER.glob("*.py")}
    graph = {}
    for path in PAPER.glob("*.py"):
        names = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
        graph[path.stem] = names & local
    return graph


def test_the_paper_suite_has_no_import_cycle():
    graph = suite_imports()
    assert {"common", "exp_aggregation", "exp_finetune", "exp_more_nodes"} <= set(graph)
    done, path = set(), []

    def visit(module):
        assert module not in path, "import cycle: " + " -> ".join(path[path.index(module):] + [module])
        if module in done:
            return
        path.append(module)
        for other in sorted(graph[module]):
            visit(other)
        path.pop()
        done.add(module)

    for module in sorted(graph):
        visit(module)


def test_experiments_import_only_the_shared_modules():
    for module, imports in suite_imports().items():
        if module.startswith("exp_") or module == "run_all":
            assert imports <= SHARED, f"{module} imports {sorted(imports - SHARED)}"
