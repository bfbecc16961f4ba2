"""The documentation site as a reader sees it: built with ``mkdocs build --strict`` (a warning fails
it), every public name of every public module has its entry in the API reference, every link and
image inside the site resolves (anchors included), the topic map covers the public API exactly, the
code on the pages runs (the migration guides compare diffquat with each peer), and, rendered by
headless Chromium from a local server, the math is typeset, no notebook output looks like an error,
and nothing is loaded from another host."""

from __future__ import annotations

import functools
import html
import http.server
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path
from types import ModuleType
from urllib.parse import unquote, urlsplit

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def api_topics() -> ModuleType:
    spec = importlib.util.spec_from_file_location("api_topics", DOCS / "api_topics.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_public_name_is_in_exactly_one_topic() -> None:
    """A new public name fails here (and fails the docs build) until docs/api_topics.py places it."""
    topics = api_topics()
    assert topics.problems() == []
    topics.topic_of()  # raises for a name placed twice


class _Page(HTMLParser):
    """The ids of one HTML page, and the links and images it points to."""

    def __init__(self) -> None:
        super().__init__()
        self.ids: set[str] = set()
        self.links: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        found = dict(attrs)
        for key in ("id", "name"):
            if found.get(key):
                self.ids.add(str(found[key]))
        for key in ("href", "src"):
            if tag in ("a", "img", "link", "script") and found.get(key):
                self.links.append(str(found[key]))


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("site")
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return out


def parse(site: Path) -> dict[Path, _Page]:
    pages = {}
    for path in site.rglob("*.html"):
        page = _Page()
        page.feed(path.read_text())
        pages[path] = page
    return pages


def test_site_builds_with_every_public_name_and_every_link_resolving(site: Path) -> None:
    pages = parse(site)
    ids = set().union(*(p.ids for p in pages.values()))
    missing = [
        f"{m.__name__}.{name}"
        for m in api_topics().public_modules()
        for name in m.__all__
        if f"{m.__name__}.{name}" not in ids
    ]
    assert not missing, f"public names without an entry in the API reference: {missing}"
    broken = []
    for path, page in pages.items():
        for link in page.links:
            parts = urlsplit(link)
            if parts.scheme or link.startswith("//"):
                continue  # outside the site
            # "/x" (the 404 page's links, which are served from anywhere) from the site's root
            base = site if parts.path.startswith("/") else path.parent
            target = path if not parts.path else (base / unquote(parts.path).lstrip("/")).resolve()
            if target.is_dir():
                target = target / "index.html"
            if not target.exists():
                broken.append(f"{path.relative_to(site)}: {link}")
            elif (
                parts.fragment
                and target.suffix == ".html"
                and unquote(parts.fragment) not in pages[target].ids
            ):
                broken.append(f"{path.relative_to(site)}: {link} (no such anchor)")
    assert not broken, "\n".join(broken)
    # The notebooks are rendered with their figures, the benchmark results with their plots.
    for name in (
        "fit_orientation",
        "pose_regression",
        "robot_orientation",
        "probabilistic_pose",
        "rotation_diffusion",
    ):
        assert "data:image/png;base64" in (site / "notebooks" / name / "index.html").read_text(), name
    assert (site / "benchmarks" / "results.png").exists()


# Each page's python blocks run in order in one namespace, in a fresh process (no test
# configuration: the snippets run as a reader's would).
PAGES_WITH_CODE = [
    "index.md",
    "objects.md",
    *(f"coming-from/{p.name}" for p in sorted((DOCS / "coming-from").glob("*.md"))),
]
RUNNER = """
import json, re, sys, traceback
failures = {}
for page in sys.argv[1:]:
    scope = {}
    for i, block in enumerate(re.findall(r"```python\\n(.*?)```", open(page).read(), re.S)):
        try:
            exec(compile(block, f"{page} block {i}", "exec"), scope)
        except Exception:
            failures[page] = traceback.format_exc(limit=4)
            break
print(json.dumps(failures))
"""


def test_the_code_on_the_pages_runs_and_matches_the_peers() -> None:
    """The migration guides' snippets assert diffquat's results against each peer's (scipy, roma,
    kornia, jaxlie, pytorch-kinematics: the test extra installs them; pytorch3d's page checks its
    documented layout without it), and the home page's quick start runs."""
    pages = [str(DOCS / p) for p in PAGES_WITH_CODE]
    assert len(pages) == 8
    for page in pages:
        assert "```python" in Path(page).read_text(), page
    result = subprocess.run([sys.executable, "-c", RUNNER, *pages], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-3000:]
    failures = json.loads(result.stdout.strip().splitlines()[-1])
    assert not failures, "\n\n".join(f"{page}:\n{trace}" for page, trace in failures.items())


def test_readme_links_into_the_docs_resolve() -> None:
    readme = (ROOT / "README.md").read_text()
    targets = re.findall(r"\]\(((?:docs|notebooks|benchmarks)/[^)#]+)", readme)
    assert any(t.startswith("docs/") for t in targets)
    assert [t for t in targets if not (ROOT / t).exists()] == []


# ---------------------------------------------------------------------------------------------------
# The site as a reader's browser shows it: headless Chromium (Debian's ``chromium``;
# scripts/install-test-tools installs it) loads the built site from a local HTTP server, with every
# other host unreachable, and its DOM after the scripts ran (MathJax included) is read.


class _Served:
    """The built site on an HTTP server of 127.0.0.1, and the status of each request it answered."""

    def __init__(self, site: Path) -> None:
        self.requests: list[tuple[str, int]] = []
        requests = self.requests

        class Handler(http.server.SimpleHTTPRequestHandler):
            def log_request(self, code: int | str = "-", size: int | str = "-") -> None:
                requests.append((self.path, int(code)))

        self.server = http.server.ThreadingHTTPServer(
            ("127.0.0.1", 0), functools.partial(Handler, directory=str(site))
        )
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def url(self, page: str) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/{page}"


@pytest.fixture(scope="module")
def served(site: Path) -> Iterator[_Served]:
    server = _Served(site)
    yield server
    server.server.shutdown()
    server.server.server_close()


@pytest.fixture(scope="module")
def chromium() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        message = "chromium is not installed (scripts/install-test-tools installs it)"
        if os.environ.get("CI"):
            pytest.fail(message + ": CI must render the site")
        pytest.skip(message)
    return found


def _browse(chromium: str, url: str, *what: str) -> subprocess.CompletedProcess[str]:
    """One headless Chromium run on ``url``: ``--dump-dom`` or ``--screenshot=...``. Virtual time runs
    until the page is idle (its scripts, MathJax's typesetting and its fonts) or 15 s have passed;
    every host but 127.0.0.1 fails to resolve, so the page can load nothing from elsewhere."""
    flags = [
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        "--window-size=1280,900",
        "--virtual-time-budget=15000",
        "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
    ]
    return subprocess.run([chromium, *flags, *what, url], capture_output=True, text=True, timeout=120)


class _Assets(HTMLParser):
    """The scripts and stylesheets a page loads."""

    def __init__(self) -> None:
        super().__init__()
        self.loads: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        found = dict(attrs)
        if tag == "script" and "src" in found:
            self.loads.append(found["src"] or "")
        if tag == "link" and found.get("rel") in ("stylesheet", "preload", "modulepreload"):
            self.loads.append(found.get("href") or "")


def test_pages_load_only_the_sites_own_scripts_and_stylesheets(site: Path) -> None:
    """No script or stylesheet with an empty address (mkdocs-jupyter's MathJax loader had one), and
    none from another host (a CDN, web fonts): the site reads the same offline."""
    wrong = []
    for path in sorted(site.rglob("*.html")):
        assets = _Assets()
        assets.feed(path.read_text())
        wrong += [f"{path.relative_to(site)}: {a!r}" for a in assets.loads if not a or urlsplit(a).netloc]
    assert not wrong, "\n".join(wrong)


# A page of math and notebook pages (their markdown writes $...$; the first two printed progress bars
# to stderr): each with the least number of typeset expressions it shows.
MATH_PAGES = {"conventions/": 10, "notebooks/fit_orientation/": 5, "notebooks/pose_regression/": 1}
HIDDEN = re.compile(r"<(mjx-container|pre|code|script|style|textarea)\b.*?</\1>", re.S)
RAW_TEX = re.compile(r"\\[(\[]|\$\$|\$[^$\s][^$]*\$")


@pytest.mark.parametrize("page", sorted(MATH_PAGES))
def test_math_is_typeset_and_no_output_is_an_error_box(
    page: str, site: Path, served: _Served, chromium: str
) -> None:
    """What a reader sees: every formula typeset by MathJax (served by the site itself), no TeX left
    as text, no TeX error; on a notebook page no output shown as an error (stderr) box; and every
    file the page asked for was there."""
    served.requests.clear()
    dom = _browse(chromium, served.url(page), "--dump-dom").stdout
    assert "</html>" in dom, "chromium rendered nothing"
    typeset = dom.count("<mjx-container")
    assert typeset >= MATH_PAGES[page], f"{typeset} formulas typeset"
    if not page.startswith("notebooks/"):  # one formula per arithmatex element
        assert typeset == (site / page / "index.html").read_text().count('class="arithmatex"')
    assert "<mjx-merror" not in dom and "data-mjx-error" not in dom, "a TeX error"
    text = html.unescape(re.sub(r"<[^>]+>", " ", HIDDEN.sub(" ", dom)))
    assert RAW_TEX.findall(text) == [], "TeX left as text"
    stderr_boxes = re.findall(r'<[^>]+data-mime-type="application/vnd\.jupyter\.stderr"', dom)
    assert stderr_boxes == [], "an output shown as an error box"
    failed = [(path, code) for path, code in served.requests if code >= 400]
    assert served.requests and not failed, failed


# The pages a newcomer opens first, and an element each must show once rendered.
RENDERED = {
    "": 'id="quick-start"',
    "api/torch/": 'id="diffquat.torch.quaternion_to_matrix"',
}


@pytest.mark.parametrize("page", sorted(RENDERED))
def test_pages_render_in_a_headless_browser(
    page: str, served: _Served, chromium: str, tmp_path: Path
) -> None:
    """The home page and the torch API page: the DOM after the theme's scripts ran holds the page's
    content, and the screenshot shows the theme's coloured header bar above dark text on a light
    page, the layout a reader gets (an unstyled page, a missing stylesheet or a blank render fail)."""
    import matplotlib.image

    dom = _browse(chromium, served.url(page), "--dump-dom")
    assert RENDERED[page] in dom.stdout, dom.stderr[-2000:]
    shot = tmp_path / "page.png"
    _browse(chromium, served.url(page), f"--screenshot={shot}").check_returncode()
    rgb = matplotlib.image.imread(shot)[..., :3]
    assert rgb.shape[:2] == (900, 1280)
    header, body = rgb[5:40], rgb[60:]
    header_colour = np.median(header.reshape(-1, 3), axis=0)
    assert header_colour.max() - header_colour.min() > 0.2, "the header bar has the theme's colour"
    assert np.mean(np.all(np.abs(header - header_colour) < 0.05, axis=-1)) > 0.8
    brightness = body.mean(axis=-1)
    assert np.mean(brightness > 0.9) > 0.5, "a light page"
    assert 0.005 < np.mean(brightness < 0.4) < 0.3, "dark text on it"
