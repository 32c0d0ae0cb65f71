"""MkDocs hook (mkdocs.yml ``hooks:``): the site carries its own MathJax, so math renders offline.

MathJax 3.2.2's files come from the ``django-static-mathjax`` wheel (in the ``docs`` extra; it is
MathJax's release as package data and needs no Django). The hook adds to the site's files, under
:data:`SITE_FOLDER`, the component that mkdocs.yml's ``extra_javascript`` loads and what that
component loads on demand from beside itself: its CHTML fonts, the TeX extensions that ``autoload``
fetches, MathML entities, the menu, and the accessibility and speech parts the menu can switch on.
``mkdocs build`` copies them into the site and ``mkdocs serve`` serves them, as it would files in
docs/; nothing is committed and no page loads anything from the network.
"""

from __future__ import annotations

from importlib.resources import files as package_files
from pathlib import Path

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

#: Where the site carries MathJax's ``es5`` folder (a subset of it, :data:`PARTS`).
SITE_FOLDER = "javascripts/mathjax"
#: The files and folders of MathJax's ``es5`` folder that the site needs: the combined component
#: (TeX and MathML in, CHTML out) and what it loads lazily. Not the other combined components, the
#: SVG output or the node adaptors.
PARTS = ("tex-mml-chtml.js", "input/tex", "input/mml", "output/chtml", "ui", "a11y", "sre")


def mathjax_folder() -> Path:
    """The installed MathJax release's folder (``package.json``, ``LICENSE``, ``es5/``)."""
    try:
        folder = Path(str(package_files("mathjax") / "static" / "mathjax"))
    except ModuleNotFoundError as error:
        raise ModuleNotFoundError(
            "the docs site carries MathJax from django-static-mathjax: pip install '.[docs]'"
        ) from error
    if not (folder / "es5" / PARTS[0]).is_file():
        raise FileNotFoundError(f"no MathJax es5/{PARTS[0]} in {folder}: is django-static-mathjax installed?")
    return folder


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add MathJax's :data:`PARTS` and its licence to the site's files under :data:`SITE_FOLDER`."""
    folder = mathjax_folder()
    es5 = folder / "es5"
    sources = [(es5 / part).rglob("*") if (es5 / part).is_dir() else [es5 / part] for part in PARTS]
    for source in (path for paths in sources for path in paths if path.is_file()):
        uri = f"{SITE_FOLDER}/{source.relative_to(es5).as_posix()}"
        files.append(File.generated(config, uri, abs_src_path=str(source)))
    files.append(File.generated(config, f"{SITE_FOLDER}/LICENSE", abs_src_path=str(folder / "LICENSE")))
    return files
