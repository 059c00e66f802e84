"""The documentation: README's headline numbers and the reference pages follow what they are generated from
(docs/gen.py), every relative link resolves, and the docs site builds with ``mkdocs build --strict``."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").rglob("*.md"))


def _load_gen() -> ModuleType:
    spec = importlib.util.spec_from_file_location("docs_gen", ROOT / "docs" / "gen.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


gen = _load_gen()


def test_generated_pages_and_readme_numbers_are_up_to_date():
    stale = [path.relative_to(ROOT).as_posix() for path, text in gen.outputs().items()
             if not path.is_file() or path.read_text() != text]
    assert not stale, f"stale: {', '.join(stale)}; run python docs/gen.py"


def test_the_readme_numbers_are_read_from_the_results_files(tmp_path):
    results = tmp_path / "results"
    shutil.copytree(ROOT / "benchmarks" / "results", results, ignore=shutil.ignore_patterns("*.txt", "*.png"))
    before = gen.results_block(README, results)
    path = results / "peer_comparison_quickstart.json"
    data = json.loads(path.read_text())
    data["cleanrl_ppo"]["target_reached"]["wall_s"] = 2 * data["ebrl"]["target_reached"]["wall_s"]
    path.write_text(json.dumps(data))
    after = gen.results_block(README, results)
    assert after != before and "(2.00x;" in after

    del data["ebrl"]["target_reached"]
    path.write_text(json.dumps(data))
    with pytest.raises(Exception, match="peer_comparison_quickstart.json: missing key 'ebrl.target_reached'"):
        gen.results_block(README, results)


def test_every_config_key_and_message_field_is_in_the_reference():
    from ebrl import config, messages

    text = (ROOT / "docs" / "reference" / "config.md").read_text()
    for name, cls in config.SECTIONS.items():
        for key in cls.__dataclass_fields__:
            assert f"| `{name}.{key}` |" in text, f"{name}.{key} is not in docs/reference/config.md"
    text = (ROOT / "docs" / "reference" / "messages.md").read_text()
    for cls in messages.MESSAGES:
        assert f"## {cls.__name__}\n" in text
        for key in cls.__dataclass_fields__:
            assert f"| `{key}` |" in text, f"{cls.__name__}.{key} is not in docs/reference/messages.md"


def test_readme_is_short_and_starts_with_its_contents():
    text = README.read_text()
    assert len(text.splitlines()) <= 450
    contents = text.split("## Contents", 1)[1].split("\n## ", 1)[0]
    anchors = {slug(h) for h in headings(text)}
    for target in re.findall(r"\]\(#([^)]+)\)", contents):
        assert target in anchors, f"README's contents link to #{target}, which no heading has"


def test_readme_shows_the_ten_line_script_the_tests_run():
    from test_portable import SCRIPT

    assert SCRIPT in README.read_text()


def test_the_stats_subscriber_is_shown_whole():
    assert (ROOT / "examples" / "subscribe_stats.py").read_text() in (ROOT / "docs" / "stats.md").read_text()


def headings(text: str) -> list[str]:
    out, fenced = [], False
    for line in text.splitlines():
        if line.startswith(("```", "~~~")):
            fenced = not fenced
        elif not fenced and re.match(r"#{1,6} ", line):
            out.append(line.lstrip("#").strip())
    return out


def slug(heading: str) -> str:
    """The anchor GitHub gives a heading."""
    text = re.sub(r"`|\*\*", "", heading).strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def links(text: str) -> list[str]:
    out, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
        elif not fenced:
            out += re.findall(r"\]\(([^)\s]+)\)", re.sub(r"`[^`]*`", "", line))
    return out


@pytest.mark.parametrize("page", [README, ROOT / "CHANGELOG.md", *PAGES], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_resolves(page):
    broken = []
    for target in links(page.read_text()):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):
            continue  # a URL
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md" and anchor not in {slug(h) for h in headings(file.read_text())}:
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: links that go nowhere: {broken}"


def test_every_docs_page_is_in_the_site_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    missing = [p.relative_to(ROOT / "docs").as_posix() for p in PAGES
               if f": {p.relative_to(ROOT / 'docs').as_posix()}\n" not in nav]
    assert not missing, f"docs pages missing from mkdocs.yml's nav: {missing}"


# the Python API page: at least these (every public name of ``import ebrl``, the test checks, and helpers beside them)
API = ("ebrl.train", "ebrl.watch", "ebrl.load_policy", "ebrl.stats.observer_config", "ebrl.metrics.describe")
_DIRECTIVE = re.compile(r"^::: ([\w.]+)\n(?:    options:\n      heading: ([\w.]+)\n(?:      \w+: .*\n)*)?", re.MULTILINE)


def api_entries() -> dict[str, str]:
    """docs/api.md's entries: the name each is shown as (its ``heading``, else its path) -> the object's path."""
    text = (ROOT / "docs" / "api.md").read_text()
    return {heading or path: path for path, heading in _DIRECTIVE.findall(text)}


def test_the_api_page_documents_each_public_name_of_ebrl_as_the_object_it_is():
    import ebrl

    entries = api_entries()
    assert set(API) <= set(entries), f"docs/api.md lacks {sorted(set(API) - set(entries))}"
    for shown, path in entries.items():
        module, _, name = path.rpartition(".")
        obj = getattr(importlib.import_module(module), name)
        public = shown.removeprefix("ebrl.")
        if shown.count(".") == 1 and public in ebrl._LAZY:
            assert getattr(ebrl, public) is obj, f"docs/api.md shows {path} as {shown}, which is another object"
        assert (obj.__doc__ or "").strip(), f"{path} has no docstring for docs/api.md"
    public = {f"ebrl.{name}" for name in ebrl._LAZY}
    assert public <= set(entries), f"public names of ebrl missing from docs/api.md: {sorted(public - set(entries))}"


def first_line(obj) -> str:
    """A docstring's first line as the built page shows it: its roles read as docs/griffe_roles.py reads them, no
    backticks or tags, spaces collapsed."""
    spec = importlib.util.spec_from_file_location("griffe_roles", ROOT / "docs" / "griffe_roles.py")
    roles = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(roles)
    line = roles.markdown(__import__("inspect").getdoc(obj).splitlines()[0])
    return " ".join(re.sub(r"</?(autoref|code)\b[^>]*>", "", line).replace("``", "").split())


@pytest.mark.slow  # a build of ~30 s (CI's slow suite runs after `make docs` installed the docs extra)
def test_the_docs_site_builds_strictly_and_works_from_disk(tmp_path):
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings_handlers") is None:
        pytest.skip("the docs extra is not installed (make docs installs it: pip install -e '.[docs]')")
    site = tmp_path / "site"
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                         cwd=ROOT, capture_output=True, text=True, timeout=600,
                         env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert (site / "reference" / "config.html").is_file() and (site / "project" / "BENCHMARKS.html").is_file()
    # every page's links name files, which a browser opens from disk (file://): no directory URL
    broken = []
    for page in sorted(site.rglob("*.html")):
        if page.name == "404.html":  # the server's page, with absolute links
            continue
        for target in re.findall(r'(?:href|src)="([^"]+)"', page.read_text()):
            path = target.split("#")[0].split("?")[0]
            if path and not re.match(r"^[a-z][a-z0-9+.-]*:|^//", target) and not (page.parent / path).is_file():
                broken.append(f"{page.relative_to(site)}: {target}")
    assert not broken, "links of the built site that are no file:\n" + "\n".join(broken[:40])
    # the API page shows each entry's docstring
    html = (site / "api.html").read_text()
    text = " ".join(__import__("html").unescape(re.sub(r"<[^>]+>", "", html)).split())
    for shown, path in api_entries().items():
        module, _, name = path.rpartition(".")
        line = first_line(getattr(importlib.import_module(module), name))
        assert shown in text and line in text, f"api.html lacks {shown} or its docstring's first line: {line!r}"
