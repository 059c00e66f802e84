"""A griffe extension (mkdocs.yml, mkdocstrings' ``extensions``) that reads the reST of EBRL's docstrings as Markdown.

The docstrings are written for a reader of the source: Sphinx roles (``:func:`ebrl.stats.stream```,
``:class:`~ebrl.config.Config```) and reST's ``::`` before a literal block. mkdocstrings renders docstrings as
Markdown, where a role would show as ``:func:`` beside its name. Here a role becomes a link to the object where the
site documents it (an optional cross-reference: plain code where it does not), and a paragraph's closing ``::``
a colon; double backticks are already code in Markdown.
"""

from __future__ import annotations

import re

import griffe

from ebrl import _LAZY  # the public names of ``ebrl`` and where each is defined (ebrl/__init__.py)

ROLE = re.compile(r":(?:py:)?(?:func|meth|class|mod|data|attr|exc|obj):`(~?)([\w.]+)(\(\))?`")
LITERAL = re.compile(r"(\S) ?::$", re.MULTILINE)  # "for example::" -> "for example:"; "::" alone stays


def defined_at(target: str, module: griffe.Module | None = None) -> str:
    """Where ``target`` is documented: ``ebrl.load_policy`` is ``ebrl.policies.portable.load_policy``; a name of
    the docstring's own ``module`` (``RunNotStarted`` in ``ebrl.api``) is that module's."""
    name = target.removeprefix("ebrl.")
    if target.startswith("ebrl.") and name in _LAZY:
        module_name, attribute = _LAZY[name] if isinstance(_LAZY[name], tuple) else (_LAZY[name], name)
        return f"{module_name}.{attribute}"
    if module is not None and target.split(".")[0] in module.members:
        return f"{module.path}.{target}"
    return target


def markdown(text: str, module: griffe.Module | None = None) -> str:
    """A docstring's reST roles and literal-block markers, as Markdown."""
    def role(match: re.Match) -> str:
        short, target = match.group(1), match.group(2)
        shown = (target.rsplit(".", 1)[-1] if short else target) + (match.group(3) or "")
        # mkdocs-autorefs: a link where the target is documented, else the text alone (no warning)
        return f'<autoref optional identifier="{defined_at(target, module)}"><code>{shown}</code></autoref>'

    return LITERAL.sub(r"\1:", ROLE.sub(role, text))


class ReSTRoles(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown(obj.docstring.value, obj.module)
