"""The layered import contract (pyproject.toml, docs/architecture.md): it holds on this tree,
and it breaks, naming the import, when an import points up, when two independent packages
meet, when the master's core imports a device, or when a new package under services/ has
no layer."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"

pytestmark = pytest.mark.skipif(
    not LINT_IMPORTS.exists(), reason="import-linter is not installed (make install)"
)


def lint(root: Path) -> tuple[int, str]:
    """`lint-imports` on the tree at `root` (its own `services`, not the installed one)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    r = subprocess.run(
        [str(LINT_IMPORTS), "--no-cache"],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    return r.returncode, r.stdout + r.stderr


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """A copy of the sources and of the contract."""
    shutil.copytree(
        ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("__pycache__")
    )
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "__init__.py").write_text("")
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_the_contract_holds_here() -> None:
    code, out = lint(ROOT)
    assert code == 0, out
    assert "7 kept, 0 broken" in out


#: (module, its text, what the report must say): one tree holds them all, so the check runs
#: once; each is a way the layers can be broken.
PLANTED = [
    # bus at the bottom imports nothing above it
    (
        "services/bus/planted.py",
        "import services.control.arm.config",
        "services.bus is not allowed",
    ),
    # a service never imports a tool (what seven mains did with cli.introspect)
    (
        "services/control/force/planted.py",
        "from services.tools.cli import introspect",
        "services.control.force.planted -> services.tools.cli.introspect",
    ),
    # the control services are independent of each other
    (
        "services/control/decision/planted.py",
        "from services.control.master import config",
        "services.control.decision is not allowed to import services.control.master",
    ),
    # a model under the services does not reach up into one, not even lazily
    (
        "services/control/arm/planted.py",
        "def f() -> None:\n    from services.control.vision import config",
        "services.control.arm is not allowed to import services.control.vision",
    ),
    # the services never import the tests' helpers
    (
        "services/world/workcell/planted.py",
        "import tests",
        "services.world.workcell.planted -> tests",
    ),
    # the master's core knows no device, not even lazily (backends.py names them)
    (
        "services/control/master/jog.py",
        "def f() -> None:\n    from services.control.master import devices",
        "services.control.master.jog -> services.control.master.devices",
    ),
    # TDPA's lab sits below the bench: the link bench uses its link, never the other way
    # (and, the tdpa contract being exhaustive, a new module in it has no place either)
    (
        "services/tools/tdpa/planted.py",
        "def f() -> None:\n    from services.tools.bench import link",
        "services.tools.tdpa is not allowed to import services.tools.bench",
    ),
    # a new package must be given its layer
    ("services/newthing/__init__.py", "", "services.newthing"),
]


def test_every_way_of_breaking_it_is_reported(tree: Path) -> None:
    for module, text, _ in PLANTED:
        (tree / module).parent.mkdir(exist_ok=True)
        (tree / module).write_text(text + "\n")
    code, out = lint(tree)
    assert code != 0
    assert "1 kept, 6 broken" in out
    missing = [said for _, _, said in PLANTED if said not in out]
    assert missing == [], out
