"""Running the code blocks of a markdown file as a user would: shell lines through the
installed `mpnode` console script, python blocks in this process (each in a fresh namespace,
in the folder), a toml block written to the file its first line names.  A block no test can
run is marked by `<!-- not run by tests: REASON -->` on the line before it."""
import os
import re
import shlex
import subprocess
import sys

MPNODE = os.path.join(os.path.dirname(sys.executable), "mpnode")

FENCE = re.compile(r"^```(\w*)\s*$")
MARK = re.compile(r"^<!-- not run by tests: (.*) -->$")


def fenced_blocks(text):
    """[(language, code, reason or None)] of every fenced block of a markdown text, in order."""
    lines = text.splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
        before = next((lines[j] for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        mark = MARK.match(before.strip())
        blocks.append((m.group(1), "\n".join(lines[i + 1:end]) + "\n", mark.group(1) if mark else None))
        i = end + 1
    return blocks


def run_shell(code, folder):
    for line in code.splitlines():
        args = shlex.split(line, comments=True)
        if not args:
            continue
        assert args[0] == "mpnode", f"a shell line the test cannot run: {line!r} (mark its block)"
        proc = subprocess.run([MPNODE, *args[1:]], cwd=folder, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f"{line}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"


def run_python(code, folder, monkeypatch):
    monkeypatch.chdir(folder)
    exec(compile(code, "<markdown>", "exec"), {"__name__": "__main__"})


def write_toml(code, folder):
    name = re.match(r"# ([\w.-]+\.toml):", code)
    assert name, f"a toml block must start with '# NAME.toml: ...':\n{code}"
    (folder / name.group(1)).write_text(code)
