"""Every ```python block of README.md runs as written and prints labelled results.

The blocks run in order in one namespace (the README says where a block continues an
earlier one), in this process (so in the suite's float64). To stay fast, the literal
problem sizes are shrunk before running, by the explicit rewrites of `SHRINK` (e.g.
`num_runs=1000` → `num_runs=8`); nothing else of a block changes.
"""

import pathlib
import re

import pytest

README = pathlib.Path(__file__).resolve().parent.parent / "README.md"
BLOCKS = re.findall(r"^```python\n(.*?)^```", README.read_text(encoding="utf-8"), flags=re.S | re.M)

# (pattern, largest value): literal sizes above the limit are lowered to it.
SHRINK = [(r"\bnum_runs=(\d+)", 8), (r"\bnum_steps=(\d+)", 100), (r"\bsteps=(\d+)", 3)]


def shrink(code: str) -> str:
    for pattern, limit in SHRINK:
        code = re.sub(pattern, lambda m, limit=limit: m.group(0).replace(m.group(1), str(min(int(m.group(1)), limit))), code)
    return code


def test_shrink_rewrites_only_the_sizes():
    code = "simulate(k, m, p, num_steps=1000, num_runs=1000)\nfit(f, o, steps=50)\nnum_steps=20\n"
    assert shrink(code) == "simulate(k, m, p, num_steps=100, num_runs=8)\nfit(f, o, steps=3)\nnum_steps=20\n"


_done: dict[int, dict] = {}


def _run_through(i: int, capsys) -> str:
    """Run blocks 0..i (those not yet run) in one shared namespace; return block i's output."""
    namespace = _done.setdefault(-1, {"__name__": "__readme__"})
    out = ""
    for j in range(i + 1):
        if j in _done:
            continue
        capsys.readouterr()
        exec(compile(shrink(BLOCKS[j]), f"README.md block {j + 1}", "exec"), namespace)
        _done[j] = namespace
        out = capsys.readouterr().out
    return out


def test_readme_has_blocks():
    assert len(BLOCKS) >= 5


# The tour runs in the default tier; the other blocks compile DR solvers for about a minute each
# on a busy 2-core machine, so they run with `-m slow`.
@pytest.mark.parametrize("i", [pytest.param(i, marks=[pytest.mark.slow] if i else []) for i in range(len(BLOCKS))])
def test_readme_block_runs_and_labels_its_output(i, capsys):
    out = _run_through(i, capsys)
    if "print(" in BLOCKS[i]:
        lines = [line for line in out.splitlines() if line.strip()]
        assert lines, f"block {i + 1} prints nothing"
        for line in lines:  # a label before the numbers, not a bare tuple or array
            assert re.match(r"\s*[^\W\d_]", line), f"block {i + 1} prints an unlabelled line: {line!r}"
