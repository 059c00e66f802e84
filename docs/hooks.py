"""MkDocs hooks (mkdocs.yml ``hooks:``): the project's top-level pages in the site, and links that work both
on GitHub and in the site.

The guides under docs/ link to README.md, BENCHMARKS.md and CHANGELOG.md as ``../BENCHMARKS.md``, which is
right in the repository but outside MkDocs' docs_dir. These hooks add those files (and the plots
BENCHMARKS.md shows) to the site under ``project/``, and rewrite every relative link, in the guides and in
those files alike, from where the target is in the repository to where it is in the site. A link to a file
that is in neither stays as written, and ``mkdocs build --strict`` fails on it.
"""
from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
PROJECT = "project"  # where the top-level files go in the site
TOP_LEVEL = ("README.md", "BENCHMARKS.md", "CHANGELOG.md")
PLOTS = "benchmarks/results"  # BENCHMARKS.md's plots
LINK = re.compile(r"(\]\()([^)\s]+)(\))")
FENCE = re.compile(r"^(```|~~~)")


def repo_path(src_uri: str) -> str:
    """Where a site file is in the repository."""
    if src_uri.startswith(PROJECT + "/"):
        return src_uri[len(PROJECT) + 1:]
    return "docs/" + src_uri


def site_uri(path: str) -> str | None:
    """Where a repository file is in the site (None: not in it)."""
    if path.startswith("docs/"):
        return path[len("docs/"):]
    if path in TOP_LEVEL or path.startswith(PLOTS + "/"):
        return f"{PROJECT}/{path}"
    return None


def on_files(files: Files, config) -> Files:
    extra = [ROOT / name for name in TOP_LEVEL] + sorted((ROOT / PLOTS).glob("*.png"))
    for path in extra:
        files.append(File.generated(config, site_uri(path.relative_to(ROOT).as_posix()), abs_src_path=str(path)))
    return files


def rewrite(target: str, page_uri: str) -> str:
    """A link of the page at ``page_uri`` (a site path), pointed at where its target is in the site."""
    if re.match(r"^[a-z][a-z0-9+.-]*:|^#|^/", target):
        return target  # a URL, an anchor on the same page, an absolute path
    path, _, anchor = target.partition("#")
    here = posixpath.dirname(repo_path(page_uri))
    resolved = posixpath.normpath(posixpath.join(here, path))
    uri = site_uri(resolved)
    if uri is None:
        return target
    relative = posixpath.relpath(uri, posixpath.dirname(page_uri) or ".")
    return relative + (f"#{anchor}" if anchor else "")


def on_page_markdown(markdown: str, page, config, files) -> str:
    lines, fenced = [], False
    for line in markdown.split("\n"):
        if FENCE.match(line.lstrip()):
            fenced = not fenced
        if not fenced:
            line = LINK.sub(lambda m: m.group(1) + rewrite(m.group(2), page.file.src_uri) + m.group(3), line)
        lines.append(line)
    return "\n".join(lines)
