"""Every table in docs/ is what scripts/regenerate_tables.py writes from the committed results."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parent.parent / "docs"


@pytest.fixture(scope="module")
def regenerate_tables():
    path = DOCS.parent / "scripts" / "regenerate_tables.py"
    spec = importlib.util.spec_from_file_location("regenerate_tables", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_tables_equal_what_the_script_writes(regenerate_tables, tmp_path):
    tables = regenerate_tables.regenerate(DOCS, tmp_path)
    # docs/runs/ holds run data, not tables
    committed = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*table*.md") if "runs" not in p.relative_to(DOCS).parts}
    assert committed == set(tables), "a table in docs/ has no generator, or a generated one is not committed"
    for name, text in tables.items():
        assert (DOCS / name).read_text() == text == (tmp_path / name).read_text(), (
            f"docs/{name} is out of date: python scripts/regenerate_tables.py"
        )
    assert (tmp_path / regenerate_tables.TRAINING_FOLDER / "training_curves.png").exists()  # the table's figure comes with it

