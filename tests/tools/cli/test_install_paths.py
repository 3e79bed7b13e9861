"""The install-path docs match the paths the configurations read (issue 23 item 12).

docs/deploy.md's "Where each file comes from" table maps every file of an installed host
(`/etc/telerobot/…`) to its source in the repository. Every `/etc/telerobot/` file that a
profile, Zenoh JSON5, unit or compose file in deploy/ names must be in it, and every source
it names must exist (or come from make-certs.sh).
"""

from __future__ import annotations

import re
from pathlib import Path

from tests.bus.test_router import REPO

DEPLOY = REPO / "deploy"
DOCS = REPO / "docs" / "deploy.md"
PATH_RE = re.compile(r"/etc/telerobot/[A-Za-z0-9._/-]*[A-Za-z0-9_-]")


def table() -> dict[str, str]:
    """Host path → source, from the docs' table (a cell may list `a`, `b` in one folder)."""
    text = DOCS.read_text()
    start = text.index("**Where each file comes from.**")
    rows: dict[str, str] = {}
    for line in text[start:].splitlines()[1:]:
        if rows and not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) != 2 or not cells[0].startswith("`/etc/telerobot/"):
            continue
        names = re.findall(r"`([^`]+)`", cells[0])
        folder = names[0].rsplit("/", 1)[0]
        for name in names:
            rows[name if name.startswith("/") else f"{folder}/{name}"] = cells[1]
    return rows


def read_by_configs() -> set[str]:
    """Every /etc/telerobot/ file named in deploy/ (folders themselves left out)."""
    found: set[str] = set()
    for f in DEPLOY.rglob("*"):
        if f.is_file() and f.suffix in {".toml", ".json5", ".service", ".yml", ".conf", ".target"}:
            found |= {p for p in PATH_RE.findall(f.read_text()) if Path(p).suffix}
    return found


def test_the_table_names_every_file_the_configurations_read() -> None:
    docs = table()
    read = read_by_configs()
    assert {"/etc/telerobot/robot.toml", "/etc/telerobot/zenoh/users.txt"} <= read
    assert sorted(read - set(docs)) == []


def test_every_source_in_the_table_exists() -> None:
    docs = table()
    assert len(docs) >= 12
    for host_path, source in docs.items():
        files = re.findall(r"`(deploy/[^`]+)`", source)
        if "make-certs.sh" in source:
            assert host_path.startswith("/etc/telerobot/certs/"), host_path
            continue
        assert files, f"{host_path}: no source named"
        for f in files:
            assert (REPO / f).is_file(), f"{host_path}: {f} does not exist"
            assert Path(f).name == Path(host_path).name, "installed under its own name"
