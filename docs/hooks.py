"""mkdocs hooks (mkdocs.yml): the API pages generated from the public modules, and the files that live
outside docs/ (the notebooks, the benchmark results) added to the site at their own paths.

An API page holds a marker ``<!-- api diffquat.torch -->``: it becomes the module's docstring, then,
topic by topic (docs/api_topics.py), one mkdocstrings entry per name of the module's ``__all__``, and
the same for each of its public submodules (so ``diffquat.torch.nn``, and any submodule added later,
lands on the torch page). ``<!-- api diffquat shallow -->`` leaves the submodules out. A public name
in no topic fails the build.

Math is typeset by MathJax 3, served from the site itself (nothing is fetched from another host): its
files come from the ``django-static-mathjax`` package (the docs extra installs it; it holds MathJax's
own build and depends on nothing, Django included), and ``docs/javascripts/mathjax.js`` configures it
for every page, the notebook pages included.
"""

from __future__ import annotations

import ast
import importlib.util
import re
import shutil
import sys
import typing
from pathlib import Path
from types import ModuleType
from typing import Any

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]
# Outside docs/, published at the same paths as in the repository (so their relative links hold).
EXTERNAL = ["notebooks/*.ipynb", "notebooks/figures/*.png", "benchmarks/*.md", "benchmarks/*.png"]
MARKER = re.compile(r"<!-- api (?P<module>[\w.]+)(?P<shallow> shallow)? -->")
# Where the site serves MathJax (mkdocs.yml's extra_javascript loads MATHJAX / "tex-chtml.js"), and
# what of MathJax's es5 build it needs: the TeX-to-HTML bundle, and the folders that bundle loads from
# at run time (the HTML output's fonts, TeX packages loaded on first use, the menu, assistive MathML).
MATHJAX = "assets/mathjax"
MATHJAX_PARTS = ["tex-chtml.js", "output/chtml", "input/tex/extensions", "ui", "a11y"]


def _topics() -> ModuleType:
    spec = importlib.util.spec_from_file_location("api_topics", Path(__file__).parent / "api_topics.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["api_topics"] = module
    spec.loader.exec_module(module)
    return module


def on_config(config: Any) -> Any:
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))  # the diffquat of this checkout
    problems = _topics().problems()
    if problems:
        raise SystemExit("API topics incomplete:\n  " + "\n  ".join(problems))
    return config


@event_priority(100)  # before mkdocs-jupyter looks for the notebooks among the files
def on_files(files: Files, config: Any) -> Files:
    for pattern in EXTERNAL:
        for path in sorted(ROOT.glob(pattern)):
            # A file of the repository's root as its source folder (not File.generated: mkdocs-jupyter
            # reads a notebook's source path from its folder, which a generated file has none of).
            uri = path.relative_to(ROOT).as_posix()
            files.append(File(uri, str(ROOT), config["site_dir"], config["use_directory_urls"]))
    es5 = _mathjax_es5()
    for part in MATHJAX_PARTS:
        for path in [es5 / part] if (es5 / part).is_file() else sorted((es5 / part).rglob("*.*")):
            uri = f"{MATHJAX}/{path.relative_to(es5).as_posix()}"
            files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files


def _mathjax_es5() -> Path:
    """MathJax's es5 build, as the django-static-mathjax package installs it."""
    spec = importlib.util.find_spec("mathjax")
    es5 = Path(spec.origin).parent / "static" / "mathjax" / "es5" if spec and spec.origin else None
    if es5 is None or not (es5 / "tex-chtml.js").is_file():
        raise SystemExit(
            'MathJax not found: the docs extra installs it (pip install -e ".[docs]", which brings the '
            "django-static-mathjax package); the site serves it itself"
        )
    return es5


def _module_markdown(module: ModuleType, topic_of: dict[str, str], order: list[str]) -> str:
    name = module.__name__
    parts = [
        f"## `{name}`\n",
        f"::: {name}\n    options:\n      members: false\n      show_root_heading: false\n"
        "      show_root_toc_entry: false\n",
    ]
    for topic in order:
        names = [n for n in topic_of if topic_of[n] == topic and n in module.__all__]
        if not names:
            continue
        parts.append(f"### {topic} {{ #{name}--{_slug(topic)} }}\n")
        for n in names:
            if typing.get_origin(getattr(module, n)) is typing.Literal:
                parts.append(_literal_markdown(name, n, getattr(module, n)))
            elif any(
                base.__module__ == "diffquat._objects" for base in getattr(getattr(module, n), "__mro__", ())
            ):
                # a backend's SO3 and SE3 are subclasses that bind the backend: their methods are
                # written once, in the base class (diffquat/_objects.py)
                parts.append(
                    f"::: {name}.{n}\n    options:\n      heading_level: 4\n      inherited_members: true\n"
                )
            else:
                parts.append(f"::: {name}.{n}\n    options:\n      heading_level: 4\n")
    return "\n".join(parts)


def _literal_markdown(module: str, name: str, alias: Any) -> str:
    """A ``Literal`` type alias: its values, and the docstring that follows it in diffquat/_types.py
    (mkdocstrings reads objects at run time here, where an alias has no docstring of its own)."""
    values = ", ".join(f'`"{v}"`' for v in typing.get_args(alias))
    return f"#### `{name}` {{ #{module}.{name} }}\n\n`Literal` of {values}.\n\n{_alias_docs()[name]}\n"


def _alias_docs() -> dict[str, str]:
    """The string that follows each assignment in diffquat/_types.py (an attribute docstring), with
    its reStructuredText literals as markdown code."""
    tree = ast.parse((ROOT / "diffquat" / "_types.py").read_text())
    docs = {}
    for node, after in zip(tree.body, tree.body[1:], strict=False):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        if isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
            docs[node.target.id] = " ".join(str(after.value.value).split()).replace("``", "`")
    return docs


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")


def api_markdown(module_name: str, shallow: bool) -> str:
    """The markdown that a marker stands for."""
    topics = _topics()
    topic_of, order = topics.topic_of(), list(topics.TOPICS)
    modules = [m for m in topics.public_modules() if m.__name__ == module_name]
    if not shallow:
        modules += [m for m in topics.public_modules() if m.__name__.startswith(module_name + ".")]
    if not modules:
        raise SystemExit(f"API marker names {module_name!r}, which is no public module")
    return "\n".join(_module_markdown(m, topic_of, order) for m in modules)


def on_post_build(config: Any) -> None:
    """A notebook's page lives at ``notebooks/<name>/``, and the notebook links the script it imports
    by its bare name (``fit_orientation.py``, right beside it in the repository): the script is
    published beside the page, so that the link holds there too."""
    for notebook in ROOT.glob("notebooks/*.ipynb"):
        script = notebook.with_suffix(".py")
        if script.exists():
            target = Path(config["site_dir"]) / "notebooks" / notebook.stem / script.name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(script, target)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Files) -> str:
    return MARKER.sub(lambda m: api_markdown(m.group("module"), bool(m.group("shallow"))), markdown)


# On a notebook page, mkdocs-jupyter writes nbconvert's MathJax 2 loader, whose script has an empty
# src (its plugin passes its empty custom_mathjax_url on) and whose configuration MathJax 3 does not
# read: the page loads the site's MathJax like every other page, so the loader goes.
NBCONVERT_MATHJAX = re.compile(r"<!-- Load mathjax -->.*?<!-- End of mathjax configuration -->", re.S)
# A stream a notebook's code wrote to stderr (tqdm's progress bars): nbconvert shows it in a pink box, an
# error to a reader's eye. The notebooks' stored outputs hold none; this keeps a re-execution's out.
STDERR_OUTPUT = re.compile(
    r'<div class="jp-OutputArea-child">\s*<div class="jp-OutputPrompt jp-OutputArea-prompt"></div>\s*'
    r'<div class="[^"]*" data-mime-type="application/vnd\.jupyter\.stderr"[^>]*>\s*<pre>.*?</pre>\s*</div>\s*'
    r"</div>",
    re.S,
)


def on_page_content(html: str, page: Any, config: Any, files: Files) -> str:
    if page.file.src_uri.endswith(".ipynb"):
        html = STDERR_OUTPUT.sub("", NBCONVERT_MATHJAX.sub("", html))
    return html
