"""The documentation site's configuration (mkdocs.yml) lists every notebook: `make docs`
executes and renders each `notebooks/*.py` named in the nav (mkdocs-jupyter, with
mkdocs_hooks.py), so a new notebook missing from the nav would be left off the site (mkdocs
only logs it), and a renamed one left in the nav would break the build. Read as text: PyYAML
comes with the docs tools (requirements-dev.lock), not with the test environment."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MKDOCS_YML = ROOT / "mkdocs.yml"
NOTEBOOKS = sorted(p.name for p in (ROOT / "notebooks").glob("*.py"))


def _nav_lines():
    """The lines of mkdocs.yml's top-level `nav:` block, comments left out."""
    lines = MKDOCS_YML.read_text(encoding="utf-8").splitlines()
    start = lines.index("nav:") + 1
    block = []
    for line in lines[start:]:
        if line and not line[0].isspace() and not line.startswith("#"):
            break  # the next top-level key
        if line.strip() and not line.lstrip().startswith("#"):
            block.append(line)
    return block


def _nav_notebooks():
    return [
        match.group(1)
        for line in _nav_lines()
        if (match := re.search(r":\s*notebooks/([^/\s]+\.py)\s*$", line))
    ]


def test_notebooks_are_found():
    # Guards the glob: a moved folder would otherwise make the next test pass on nothing.
    assert NOTEBOOKS, f"no notebooks found under {ROOT / 'notebooks'}"


def test_nav_lists_every_notebook_once():
    listed = _nav_notebooks()
    assert sorted(listed) == NOTEBOOKS, (
        f"mkdocs.yml's nav (section Notebooks) must list each notebooks/*.py once as "
        f"'- Title: notebooks/<name>.py'; missing: {sorted(set(NOTEBOOKS) - set(listed))}, "
        f"not in notebooks/: {sorted(set(listed) - set(NOTEBOOKS))}, listed: {listed}"
    )


def test_notebooks_are_executed_by_the_docs_build():
    text = MKDOCS_YML.read_text(encoding="utf-8")
    assert "- mkdocs_hooks.py" in text, "mkdocs.yml must load mkdocs_hooks.py (hooks:)"
    plugin = re.search(r"^  - mkdocs-jupyter:\n((?:      .*\n)+)", text, re.MULTILINE)
    assert plugin, "mkdocs.yml must enable the mkdocs-jupyter plugin"
    settings = plugin.group(1)
    assert re.search(r"^      execute: true\b", settings, re.MULTILINE)
    assert re.search(r"^      allow_errors: false\b", settings, re.MULTILINE)
