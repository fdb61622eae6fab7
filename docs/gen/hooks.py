"""mkdocs hook: fill the pages' ``<!-- gen: ... -->`` markers from the code and bench results.

mkdocs.yml names this file under ``hooks:``; the Markdown comes from ``render.py`` beside it.
Images a page names with an ``image`` marker are copied from the repository into the site.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

sys.path.insert(0, str(Path(__file__).resolve().parent))
import render  # noqa: E402  (beside this file, not a package)


def on_files(files, config):
    """Add the repository images that pages ask for under ``assets/``."""
    docs = Path(config["docs_dir"])
    wanted = set()
    for page in docs.rglob("*.md"):
        wanted.update(render.images(page.read_text(encoding="utf-8")))
    for rel in sorted(wanted):
        files.append(File.generated(config, render.image_uri(rel),
                                    abs_src_path=str(render.ROOT / rel)))
    return files


def on_page_markdown(markdown, page, config, files):
    """Replace each marker with the generated Markdown (a marker naming nothing fails)."""
    depth = page.file.src_uri.count("/")
    try:
        return render.render_page(markdown, depth)
    except render.GenError as e:
        raise PluginError(f"docs/{page.file.src_uri}: {e}") from None
