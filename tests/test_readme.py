"""The README is read on its own (GitHub, the package index), outside the docs site: each of its
relative links and images names a file of the checkout."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_readme_relative_links_name_existing_files():
    targets = re.findall(r"\]\(([^)\s]+)\)", (REPO / "README.md").read_text())
    relative = [t.split("#")[0] for t in targets if not re.match(r"[a-z]+:|#", t)]
    assert relative, "the README links to no file of the checkout: the pattern no longer finds its links"
    missing = [t for t in relative if not (REPO / t).is_file()]
    assert not missing, f"README.md links to files that do not exist: {missing}"
