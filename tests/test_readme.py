"""The README runs as written: its snippets in order, in one folder, as a new user would run them.

Shell blocks run line by line through the installed `mpnode` console script; python blocks run
in this process, each in a fresh namespace, with the folder as the working directory; a toml
block whose first line is `# NAME: ...` is written to the file NAME.  Only the budgets and data
sizes in SHRINK change, so the test stays fast; every entry must match the README exactly once,
so the table cannot go stale.  A block no test can run is marked in the README by
`<!-- not run by tests: REASON -->` on the line before it, and NOT_RUN lists those reasons: a
new mark fails here until it is listed.
"""
import ast
import configparser
import hashlib
import re
from pathlib import Path

import pytest
from doc_snippets import fenced_blocks, run_python, run_shell, write_toml

from mpnode.data import read_trajectories

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"

#: README text -> what the test runs instead: smaller budgets and data sets, nothing else
SHRINK = {
    "coupled_pendulum -o model.h5": "coupled_pendulum -o model.h5 --trajectories 20 --epochs 2",
    "--trajectories 1000": "--trajectories 20",
    "--ensemble 5 --time-limit 10 ": "--ensemble 2 --epochs 2 ",
    "--time-limit 10m": "--epochs 2",
    "--trajectories 50 --seed 1": "--trajectories 10 --seed 1",
    "-o l10_model.h5 --time-limit 5m": "-o l10_model.h5 --epochs 2",
    "--trajectories 200 --seed 2": "--trajectories 10 --seed 2",
    '"epochs": 300': '"epochs": 2',
    "--epochs 100": "--epochs 5",
    "--time-limit 1m": "--trajectories 20 --epochs 2",
    "-B 100 --seed 5": "-B 10 --seed 5",
    "epochs = 300": "epochs = 2",
    "--trajectories 2000": "--trajectories 8",
    "pend_log.h5 -B 300": "pend_log.h5 -B 12",
    "-o pend_log_model.h5 --time-limit 5m": "-o pend_log_model.h5 --epochs 2",
    "pend_log_test.h5 -B 100": "pend_log_test.h5 -B 6",
}

#: the README's blocks that no test runs, and why
NOT_RUN = {
    "installs the package and runs the whole suite, this README's test included",
    "hours of training (tests/test_paper_quick.py runs the --quick tier)",
}

def readme_blocks(text=None):
    """[(language, code, reason or None)] of every fenced block of the README, in order."""
    return fenced_blocks(README.read_text() if text is None else text)


def shrunk(blocks):
    """The runnable blocks with SHRINK applied; each SHRINK entry must occur exactly once."""
    runnable = [(lang, code) for lang, code, reason in blocks if reason is None]
    for old in SHRINK:
        found = sum(code.count(old) for _, code in runnable)
        assert found == 1, f"SHRINK entry {old!r} occurs {found} times in the README's runnable blocks"
    out = []
    for lang, code in runnable:
        for old, new in SHRINK.items():
            code = code.replace(old, new)
        out.append((lang, code))
    return out


def digest(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.slow
def test_the_readme_runs_as_written_in_one_folder(tmp_path, monkeypatch):
    pytest.importorskip("matplotlib", reason="the README draws figures: the plot extra is not installed")
    pytest.importorskip("onnx", reason="the README exports to ONNX: the onnx extra is not installed")
    blocks = readme_blocks()
    assert {reason for _, _, reason in blocks if reason} == NOT_RUN
    trained = None
    for lang, code in shrunk(blocks):
        if lang == "":
            run_shell(code, tmp_path)
        elif lang == "python":
            run_python(code, tmp_path, monkeypatch)
        elif lang == "toml":
            write_toml(code, tmp_path)
        else:
            pytest.fail(f"a README block in {lang!r}, which this test does not know how to run")
        if trained is None and (tmp_path / "model.h5").exists():
            trained = digest(tmp_path / "model.h5")
    # the main job's model is still the one it trained: no later snippet wrote over it
    assert trained == digest(tmp_path / "model.h5")
    for name in ("python_model.h5", "library_model.h5", "l10_model.h5", "springs_model.h5",
                 "train.png", "eval.png", "simulate.png", "sweep_out/summary.csv"):
        assert (tmp_path / name).exists(), name
    springs = read_trajectories(tmp_path / "springs.h5")
    assert springs.system == "springs" and springs.n_nodes == 5


def test_every_not_run_block_is_marked_and_listed():
    text = "<!-- not run by tests: why -->\n```\nmpnode x\n```\n\n```python\nprint(1)\n```\n"
    assert readme_blocks(text) == [("", "mpnode x\n", "why"), ("python", "print(1)\n", None)]


def test_the_readme_is_a_short_manual():
    lines = README.read_text().splitlines()
    assert len(lines) <= 250
    assert max(map(len, lines)) <= 200, "a README line over 200 characters: move the detail to docs/"


def test_ci_runs_the_readme_install_and_test_commands():
    """.ci/run installs from this repository into a fresh venv with exactly the README's
    commands: the default tier (`pytest`) and the slow tier (`pytest -m slow`), which setup.cfg
    leaves out of the first; so between them CI runs every test, and nothing a contributor does not."""
    install = [code for _, code, reason in readme_blocks() if reason and reason.startswith("installs")]
    assert len(install) == 1
    readme = install[0].splitlines()
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    for line in readme:
        assert line in ci, f"{line!r} is in the README's install block but not in .ci/run"
    assert "python3 -m venv .venv" in ci
    tests = [line for line in readme if line.startswith("pytest")]
    assert tests == ["pytest", "pytest -m slow"]
    assert [line for line in ci if line.startswith("pytest")] == tests
    config = configparser.ConfigParser()
    config.read(ROOT / "setup.cfg")
    assert '-m "not slow"' in config["tool:pytest"]["addopts"]
    assert "slow:" in config["tool:pytest"]["markers"]


def test_the_slow_tier_has_tests_that_need_no_extra():
    """`pytest -m slow` must collect a test whatever extras are installed (pytest exits 5 when it
    collects none): some test is marked slow and nothing else, in a module that skips nothing at import."""
    def names(node):
        return {n.attr if isinstance(n, ast.Attribute) else n.id for n in ast.walk(node)
                if isinstance(n, (ast.Attribute, ast.Name))}

    def mark(decorator):  # pytest.mark.slow -> "slow", @pytest.mark.parametrize(...) -> "parametrize"
        f = decorator.func if isinstance(decorator, ast.Call) else decorator
        return f.attr if isinstance(f, ast.Attribute) else f.id

    found = []
    for path in sorted(Path(__file__).parent.glob("test_*.py")):
        module = ast.parse(path.read_text())
        if any(names(n) & {"importorskip", "skip", "pytestmark"} for n in module.body
               if not isinstance(n, (ast.FunctionDef, ast.ClassDef))):
            continue
        for fn in module.body:
            if isinstance(fn, ast.FunctionDef) and fn.name.startswith("test_"):
                if {mark(d) for d in fn.decorator_list} - {"parametrize"} == {"slow"} \
                        and not names(fn) & {"importorskip", "skip"}:
                    found.append(f"{path.name}::{fn.name}")
    assert found


ISSUE = re.compile(r"\bissues?[ -]?#?\d+", re.IGNORECASE)
DATE = re.compile(r"\b(?:19|20)\d\d-\d\d-\d\d\b")


EVIDENCE = ROOT / "docs" / "evidence"


@pytest.mark.parametrize("path", [README, *sorted((ROOT / "docs").rglob("*.md")),
                                  *sorted((ROOT / "benchmarks").rglob("*.md"))],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_the_docs_speak_of_the_project_not_its_history(path):
    """No issue numbers in user-facing text, no pointer outside the repository, and dates only in
    docs/evidence, where a measurement says when it was made."""
    text = path.read_text()
    assert not ISSUE.search(text), ISSUE.search(text).group(0)
    assert "../shared" not in text
    if EVIDENCE not in path.parents:
        assert not DATE.search(text), DATE.search(text).group(0)
