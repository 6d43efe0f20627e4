"""report.html in a real headless Chromium: every picture loads, the tables render,
and a screenshot is kept (under the test's tmp dir and as runs/test-artifacts/report_screenshot*.png).

Skipped, saying which package to install, where Chromium is absent; CI (.ci/run) installs it.
"""

import html
import importlib.util
import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest
from PIL import Image, ImageStat

from generator_runs import TINY
from vqtouch.plugins.cli.app import main

_SPEC = importlib.util.spec_from_file_location("report_runs", Path(__file__).with_name("report_runs.py"))
report_runs = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(report_runs)

ARTIFACTS = Path(__file__).resolve().parent.parent / "runs" / "test-artifacts"

#: Headless Chromium on a machine without network: the background-networking flags stop the
#: connections a closed network refuses; a fresh profile per call keeps runs independent.
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
]

#: Injected into a copy of the page (report.html itself runs no script): once everything has
#: loaded, what the browser made of each image and table goes into an attribute of <html>.
PROBE = """<script>
window.addEventListener("load", () => {
  const images = [...document.images].map(image => ({source: image.dataset.source, complete: image.complete,
    naturalWidth: image.naturalWidth, naturalHeight: image.naturalHeight, shownWidth: image.clientWidth}));
  const tables = [...document.querySelectorAll("main > section > table, main > section table.scores")].map(table => ({
    name: table.className, rows: table.rows.length,
    shownRows: [...table.rows].filter(row => row.getBoundingClientRect().height > 0).length}));
  // Data URIs are not network resources: anything listed here was fetched from elsewhere.
  const fetched = performance.getEntriesByType("resource").map(entry => entry.name);
  // The model scores coloured against the no-contact background, as the browser paints them.
  const marked = [...document.querySelectorAll("table.comparison td.better, table.comparison td.worse")].map(cell => ({
    verdict: cell.classList.contains("better") ? "better" : "worse", title: cell.title,
    background: getComputedStyle(cell).backgroundColor}));
  document.documentElement.setAttribute("data-probe", JSON.stringify({images, tables, fetched, marked,
    height: document.documentElement.scrollHeight}));
});
</script>"""


def chromium() -> str:
    """The Chromium executable; skips the test, naming the package, when there is none."""
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip(
        "Chromium is not installed: install the Debian package with `apt-get install chromium` "
        "to run the browser tests (CI's .ci/run does)"
    )


def run_chromium(*arguments: str) -> str:
    """Chromium's stdout for ``arguments``, with a throwaway profile."""
    with tempfile.TemporaryDirectory(prefix="vqtouch-chromium-") as profile:
        result = subprocess.run(
            [chromium(), *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *arguments],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def probe(report: Path, scratch: Path) -> dict:
    """Load a copy of ``report`` with :data:`PROBE` added and return what the probe saw."""
    probed = scratch / "probed.html"
    probed.write_text(report.read_text(encoding="utf-8").replace("</body>", PROBE + "</body>"), encoding="utf-8")
    dom = run_chromium("--window-size=1280,800", "--virtual-time-budget=5000", "--dump-dom", probed.as_uri())
    found = re.search(r'data-probe="([^"]*)"', dom)
    assert found, "the page never finished loading (no probe result in the DOM)"
    return json.loads(html.unescape(found.group(1)))


def screenshot(report: Path, height: int, path: Path) -> Path:
    """A full-page screenshot of ``report`` at 1280 px wide, written to ``path`` and kept as an
    artifact in runs/test-artifacts/ (gitignored)."""
    height = max(600, min(height, 12000))
    run_chromium(f"--window-size=1280,{height}", f"--screenshot={path}", "--virtual-time-budget=5000", report.as_uri())
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(path, ARTIFACTS / path.name)
    return path


def assert_rendered(seen: dict, pictures: set[str]) -> None:
    """Nothing was fetched, every image loaded with its natural size and is shown, every table shows
    all its rows."""
    assert seen["fetched"] == []
    assert {image["source"] for image in seen["images"]} == pictures
    for image in seen["images"]:
        assert image["complete"] and image["naturalWidth"] > 0 and image["naturalHeight"] > 0, image
        assert image["shownWidth"] > 0, image
    assert seen["tables"], "no table rendered"
    for table in seen["tables"]:
        assert table["rows"] >= 2 and table["shownRows"] == table["rows"], table


def assert_not_blank(path: Path) -> None:
    with Image.open(path) as image:
        assert image.format == "PNG" and image.width == 1280
        assert max(ImageStat.Stat(image.convert("L")).stddev) > 10  # text, tables and pictures, not an empty page


def test_the_synthetic_report_renders_in_chromium(tmp_path):
    run = report_runs.synthetic_run(tmp_path / "run")
    assert main(["report", str(run)]) == 0
    seen = probe(run / "report.html", tmp_path)
    assert_rendered(seen, set(report_runs.PICTURES) | {"metrics.jsonl"})
    natural = {image["source"]: (image["naturalWidth"], image["naturalHeight"]) for image in seen["images"]}
    assert all(natural[name] == size for name, size in report_runs.PICTURES.items()), natural
    tables = {table["name"]: table["rows"] for table in seen["tables"]}
    assert tables["stages"] == 4 and tables["skipped"] == 1 + len(report_runs.SKIP_REASONS)
    # The tokenizer's and the generator's scores, each beside the no-contact background's: a header
    # and one row per score with a comparison.
    comparison_rows = [table["rows"] for table in seen["tables"] if table["name"] == "scores comparison"]
    assert comparison_rows == [1 + 3, 1 + 2]
    # Better and worse are painted in two different, visible colours (psnr 29.16 < 31.60: worse).
    colours = {cell["verdict"]: cell["background"] for cell in seen["marked"]}
    assert set(colours) == {"better", "worse"} and colours["better"] != colours["worse"]
    assert "rgba(0, 0, 0, 0)" not in colours.values()
    assert all(cell["title"].startswith(f"{cell['verdict']} than the no-contact background") for cell in seen["marked"])
    assert_not_blank(screenshot(run / "report.html", seen["height"], tmp_path / "report_screenshot_synthetic.png"))


def test_a_tiny_demo_ends_in_a_report_that_renders_in_chromium(tmp_path, capsys):
    out = tmp_path / "demo"
    args = [
        "--no-progress",
        "demo",
        "--scene",
        "label-to-touch",
        "--out",
        str(out),
        "--set",
        'stages=["tokenizer", "reconstruct", "generator"]',
    ]
    for override in [*TINY, "tokenizer.train.log_every=1"]:
        args += ["--set", override]
    assert main(args) == 0
    assert f"report: {out / 'report.html'}\n" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    assert 0 < report["seconds"] and 0 < report["peak_rss_mb"] and report["started"]
    assert [stage["stage"] for stage in report["stages"]] == ["tokenizer", "reconstruct", "generator"]
    assert all(stage["status"].startswith("ran") and stage["seconds"] > 0 for stage in report["stages"])
    assert sum(stage["seconds"] for stage in report["stages"]) <= report["seconds"]

    seen = probe(out / "report.html", tmp_path)
    # The three stage pictures, the sensor's ball presses, the data preview and two loss curves
    # (one per training stage).
    sources = [image["source"] for image in seen["images"]]
    assert sorted(sources) == sorted(
        [
            "reconstructions.png",
            "real_frames.png",
            "samples.png",
            "render_sensor.png",
            "preview_data_dataset.png",
            "metrics.jsonl",
            "metrics.jsonl",
        ]
    )
    assert_rendered(seen, set(sources))
    assert_not_blank(screenshot(out / "report.html", seen["height"], tmp_path / "report_screenshot.png"))
