"""The documentation site builds strictly, holds every public name, and renders math and code.

`test_site_builds_strictly` (default tier) runs `mkdocs build --strict`: a broken link, a
missing anchor, an unresolved docstring cross-reference or a README section that a page
includes but the README no longer has fails it. The oracles of its content checks are the
repository itself: the export tables of the packages, the notebooks and benchmark results on
disk, and the TeX of the math pages.

`test_site_renders_in_a_browser` (slow tier) serves the built site on the loopback address and
loads pages in headless Chromium (playwright, driving the system's `chromium`; KaTeX comes from
a local copy, e.g. Debian's `libjs-katex`: every request off the machine is blocked). It checks
in the DOM that math was typeset and code highlighted, and saves screenshots to
`$JDRKF_SCREENSHOTS` (default: the test's temporary directory).
"""

from __future__ import annotations

import ast
import functools
import html
import json
import http.server
import os
import pathlib
import re
import shutil
import subprocess
import sys
import threading

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent


def _build(site: pathlib.Path) -> subprocess.CompletedProcess:
    pytest.importorskip("mkdocs", reason="the docs extra is not installed: pip install -e '.[docs]'")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-f", str(ROOT / "mkdocs.yml"), "-d", str(site)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> pathlib.Path:
    site = tmp_path_factory.mktemp("docs") / "site"
    proc = _build(site)
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"
    return site


def _page(site: pathlib.Path, uri: str) -> str:
    return (site / uri / "index.html").read_text(encoding="utf-8")


def _reexports(init: pathlib.Path) -> list[str]:
    """Public names a package `__init__.py` binds with `from ... import X as X`."""
    tree = ast.parse(init.read_text(encoding="utf-8"))
    return [a.asname for n in tree.body if isinstance(n, ast.ImportFrom) for a in n.names
            if a.asname and not a.asname.startswith("_")]


def test_site_builds_strictly(site):
    assert (site / "index.html").is_file()
    # Every include directive was expanded (the hook fails the build otherwise; this checks it ran).
    for page in site.rglob("*.html"):
        assert "<!-- readme:" not in page.read_text(encoding="utf-8") and "<!-- report:" not in page.read_text(encoding="utf-8"), page


def test_api_reference_documents_every_public_name(site):
    exports = ast.literal_eval(re.search(r"_EXPORTS: dict\[str, str\] = (\{.*?\n\})", (ROOT / "jdrkf/__init__.py").read_text(encoding="utf-8"), re.S).group(1))
    anchors = set()
    for uri in ("api/jdrkf", "api/filters", "api/sets"):
        anchors |= set(re.findall(r'id="(jdrkf\.[\w.]+)"', _page(site, uri)))
    missing = [name for name, module in exports.items()
               if f"jdrkf.{name}" not in anchors and f"jdrkf.filters.{name}" not in anchors]
    assert not missing, f"public names without an API entry: {missing}"
    for package in ("filters", "sets"):
        names = _reexports(ROOT / "jdrkf" / package / "__init__.py")
        missing = [n for n in names if f"jdrkf.{package}.{n}" not in anchors]
        assert names and not missing, f"jdrkf.{package} names without an API entry: {missing}"
    for module, function in (("tuning", "fit"), ("metrics", "rmse"), ("linalg", "cholesky")):
        assert f'id="jdrkf.{module}.{function}"' in _page(site, f"api/{module}")


def test_every_notebook_and_benchmark_result_has_a_page(site):
    notebooks = sorted(p.stem for p in (ROOT / "notebooks").glob("*.ipynb"))
    results = sorted((ROOT / "benchmarks/results").glob("*_[cg]pu.md"))
    assert notebooks and results and any(p.name.endswith("_gpu.md") for p in results)
    for name in notebooks:
        page = _page(site, f"notebooks/{name}")
        assert "jp-Cell" in page or "jupyter-wrapper" in page, name  # rendered by mkdocs-jupyter
    for path in results:  # NAME_cpu.md -> page benchmarks/NAME, NAME_gpu.md -> benchmarks/NAME-gpu
        name = path.name.removesuffix("_cpu.md") if path.name.endswith("_cpu.md") else path.name.removesuffix("_gpu.md") + "-gpu"
        text = path.read_text(encoding="utf-8")
        title = text.splitlines()[0].removeprefix("# ")
        assert html.escape(title, quote=False) in _page(site, f"benchmarks/{name}"), name
        for figure in re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", text):  # the plots a result page shows
            assert (site / "benchmarks" / figure).is_file(), (name, figure)


def test_every_notebook_ships_executed():
    """The site renders stored outputs without running anything: each notebook must be stored
    executed, every code cell in order (the slow tier's test_notebooks.py re-runs them)."""
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = [c for c in json.loads(path.read_text(encoding="utf-8"))["cells"] if c["cell_type"] == "code"]
        counts = [c.get("execution_count") for c in cells]
        assert cells and counts == list(range(1, len(cells) + 1)), f"{path.name} is not stored executed top to bottom: {counts}"
        assert any(c.get("outputs") for c in cells), f"{path.name} has no stored outputs"


def test_math_pages_keep_their_tex_for_the_renderer(site):
    for md in sorted((ROOT / "docs/math").glob("*.md")):
        text = md.read_text(encoding="utf-8")
        blocks = len(re.findall(r"^\$\$$", text, re.M)) // 2
        page = _page(site, f"math/{md.stem}")
        # arithmatex wraps display math as \[...\] in a div and inline math as \(...\) in a span
        assert page.count('<div class="arithmatex">') == blocks, md.name
        if re.search(r"(?<![\\$])\$[^$\s][^$]*\$", text):
            assert '<span class="arithmatex">' in page, md.name


def test_no_display_math_swallows_the_next(site):
    """Two `$$…$$` lines with no blank line between them make one arithmatex block that KaTeX
    cannot parse (in docstrings too): separate them with a blank line."""
    for page in site.rglob("*.html"):
        for tex in re.findall(r'class="arithmatex">(.*?)</(?:div|span)>', page.read_text(encoding="utf-8"), re.S):
            assert "$$" not in tex, f"{page.relative_to(site)}: {tex[:200]}"


def test_readme_sections_and_reports_reach_their_pages(site):
    conventions = _page(site, "conventions")
    assert "Time index." in conventions and "nonpositive_innovation" in conventions
    tour = _page(site, "getting-started")
    assert "jdrkf.metrics.mean_ci" in html.unescape(re.sub(r"<[^>]+>", "", tour))
    for report in sorted((ROOT / "docs/reproductions").glob("*.md")):
        first = report.read_text(encoding="utf-8").splitlines()[0]
        name = re.match(r"## (\S+)", first).group(1)
        pages = [_page(site, f"papers/{p.stem}") for p in (ROOT / "docs/papers").glob("*.md") if p.stem != "index"]
        assert any(f'id="{name}' in page for page in pages), f"the report {report.name} is on no paper page"


def test_differences_table_lists_every_paper_number_outside_our_interval(site):
    import tomllib

    text = html.unescape(re.sub(r"<[^>]+>", " ", _page(site, "papers/differences")))
    spec = tomllib.loads((ROOT / "docs/reproductions/differences.toml").read_text(encoding="utf-8"))
    reports = sorted((ROOT / "docs/reproductions").glob("*.json"))
    assert reports
    listed = 0
    for path in reports:
        report = json.loads(path.read_text(encoding="utf-8"))
        assert report["experiment"] in spec["paper_runs"], path.name
        for row in report["rows"]:
            lo, hi = row["ci95"]
            outside = row["paper"] is not None and row["runs"] > 1 and not lo <= row["paper"] <= hi
            assert row["outside_ci"] == outside, (path.name, row)  # the flag agrees with the interval
            if row["paper"] is None:
                continue
            cells = f" {report['experiment']} {row['filter']} {row['metric']} {row['paper']:.4g} {row['mean']:.4g} "
            assert (re.sub(r"\s+", " ", cells) in re.sub(r"\s+", " ", text)) == outside, (path.name, row["filter"], row["metric"])
            listed += outside
    page = _page(site, "papers/differences")
    table = page[page.index("<table"):page.index("</table>")]
    cells = [re.findall(r"<td[^>]*>(.*?)</td>", row, re.S) for row in re.findall(r"<tr>(.*?)</tr>", table, re.S)][1:]
    assert len(cells) == listed and all(len(c) == 7 and c[5].strip() and c[6].strip() for c in cells)  # a cause, evidence


# ---------------------------------------------------------------------------------------------
# Headless browser (slow tier)

KATEX_DIRS = [os.environ.get("JDRKF_KATEX_DIR", ""), "/usr/share/javascript/katex"]


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.mark.slow
def test_site_renders_in_a_browser(site, tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install playwright")
    chromium = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    katex = next((pathlib.Path(d) for d in KATEX_DIRS if d and (pathlib.Path(d) / "katex.min.js").is_file()), None)
    if chromium is None or katex is None:
        pytest.skip("needs a chromium binary and a local KaTeX (apt-get install chromium libjs-katex fonts-katex)")
    shots = pathlib.Path(os.environ.get("JDRKF_SCREENSHOTS", tmp_path))
    shots.mkdir(parents=True, exist_ok=True)

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(site)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"

    def route(r):
        url = r.request.url
        if url.startswith(base):
            return r.continue_()
        m = re.match(r"https://cdn\.jsdelivr\.net/npm/katex@[^/]+/dist/(.+)", url)
        # the CDN's file, or its unminified twin (Debian ships contrib/auto-render.js only)
        local = [katex / m.group(1), katex / m.group(1).replace(".min.", ".")] if m else []
        for path in local:
            if path.is_file():
                return r.fulfill(path=str(path))
        return r.abort()  # nothing leaves the machine

    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.route("**/*", route)
            found = {}
            pages = [("front", ""), ("api_filters", "api/filters/"), ("math_wasserstein", "math/wasserstein/")]
            pages += [(f"api_{p.stem}", f"api/{p.stem}/") for p in sorted((ROOT / "docs/api").glob("*.md")) if p.stem not in ("filters", "index")]
            for name, uri in pages:
                page.goto(f"{base}/{uri}")
                page.wait_for_load_state("networkidle")
                page.wait_for_function("document.querySelectorAll('.arithmatex').length === 0 || document.querySelectorAll('.arithmatex .katex').length > 0", timeout=20_000)
                found[name] = page.evaluate("""() => ({
                    math: document.querySelectorAll('.arithmatex').length,
                    typeset: document.querySelectorAll('.arithmatex .katex').length,
                    errors: document.querySelectorAll('.katex-error').length,
                    raw: (document.querySelector('article').innerText.match(/\\\\\\(|\\\\\\[|\\$\\$/g) || []).length,
                    code: document.querySelectorAll('.highlight pre code').length,
                    tokens: document.querySelectorAll('.highlight pre code span[class]').length,
                    headings: document.querySelectorAll('.doc-heading').length,
                })""")
                page.screenshot(path=str(shots / f"{name}.png"))
            browser.close()
    finally:
        server.shutdown()
        server.server_close()

    front, api, math = found["front"], found["api_filters"], found["math_wasserstein"]
    for name, f in found.items():
        assert f["errors"] == 0 and f["raw"] == 0, (name, f)  # no KaTeX error, no TeX left as text
        assert f["typeset"] == f["math"], (name, f)  # every arithmatex element typeset
    assert front["math"] >= 1 and front["code"] >= 1 and front["tokens"] > 0, front
    assert api["headings"] > 20 and api["code"] > 20 and api["tokens"] > 0, api  # signatures, highlighted
    assert math["math"] > 20, math
    for name in found:
        assert (shots / f"{name}.png").stat().st_size > 10_000
