"""report.html: one self-contained page per demo run, rebuilt by ``vqtouch report``.
Fast checks on the markup; tests/test_report_browser.py opens the page in a real browser."""

import base64
import html
import importlib.util
import io
import json
import re
import shutil
from html.parser import HTMLParser
from pathlib import Path

from PIL import Image

from vqtouch.plugins.cli.app import main
from vqtouch.plugins.report.demo import render_report
from vqtouch.plugins.evaluation.directions import lower_is_better
from vqtouch.plugins.report.html import render_html
from vqtouch.plugins.report.results import format_value, skipped_items
from vqtouch.plugins.report.verdicts import COMPARISON_PREFIXES, contact_verdict, score_table

_SPEC = importlib.util.spec_from_file_location("report_runs", Path(__file__).with_name("report_runs.py"))
report_runs = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(report_runs)


class Page(HTMLParser):
    """What a browser would fetch or run from a page, its images, its tables' rows and its text."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str]]] = []
        self.rows_by_table: dict[str, int] = {}
        self.text_parts: list[str] = []
        self._tables: list[str] = []
        self.feed(text)
        self.close()

    def handle_starttag(self, tag, attrs):
        attributes = {name: value or "" for name, value in attrs}
        self.tags.append((tag, attributes))
        if tag == "table":
            self._tables.append(attributes.get("class", "") or f"table{len(self.tags)}")
            self.rows_by_table.setdefault(self._tables[-1], 0)
        elif tag == "tr" and self._tables:
            self.rows_by_table[self._tables[-1]] += 1

    def handle_endtag(self, tag):
        if tag == "table" and self._tables:
            self._tables.pop()

    def handle_data(self, data):
        self.text_parts.append(data)

    @property
    def text(self) -> str:
        return " ".join(" ".join(self.text_parts).split())

    def images(self) -> list[dict[str, str]]:
        return [attributes for tag, attributes in self.tags if tag == "img"]


def _decoded_png(src: str) -> bytes:
    prefix = "data:image/png;base64,"
    assert src.startswith(prefix), src[:40]
    return base64.b64decode(src[len(prefix) :], validate=True)


def test_the_report_is_one_self_contained_page_with_every_picture_embedded(tmp_path, capsys):
    run = report_runs.synthetic_run(tmp_path / "copied_run")
    assert main(["report", str(run)]) == 0
    assert capsys.readouterr().out == f"report: {run / 'report.html'}\n"
    markup = (run / "report.html").read_text(encoding="utf-8")
    page = Page(markup)

    # Nothing to fetch and nothing to run: no external URL, no style sheet link or import, no script.
    assert "@import" not in markup
    assert re.search(r"url\(\s*['\"]?(?!data:)", markup) is None
    for tag, attributes in page.tags:
        assert tag not in ("script", "link", "iframe", "object", "embed"), tag
        for name in ("src", "href", "srcset", "poster", "data", "action"):
            value = attributes.get(name, "").strip().lower()
            assert not value.startswith(("http:", "https:", "//", "ftp:", "file:")), (tag, name, value[:60])

    # Every picture the report names (one recorded under the run's original folder) plus the
    # training-loss curve, each a data: URI of the file's very bytes.
    by_source = {image["data-source"]: image for image in page.images()}
    assert set(by_source) == set(report_runs.PICTURES) | {"metrics.jsonl"}
    for name, size in report_runs.PICTURES.items():
        data = _decoded_png(by_source[name]["src"])
        assert data == (run / name).read_bytes(), name
        with Image.open(io.BytesIO(data)) as image:
            assert image.format == "PNG" and image.size == size, name
    with Image.open(io.BytesIO(_decoded_png(by_source["metrics.jsonl"]["src"]))) as curve:
        assert curve.format == "PNG" and curve.size[0] > 200

    # The header, the tables (header row + one per entry) and the captions.
    text = page.text
    for fact in ("label-to-touch", "2025-01-02 03:04", "1 min 23 s", "1,536 MB"):
        assert fact in text, fact
    assert page.rows_by_table["stages"] == 1 + 3 and page.rows_by_table["components"] == 1 + 3
    assert page.rows_by_table["skipped"] == 1 + len(report_runs.SKIP_REASONS)
    assert page.rows_by_table["sanity"] == 1 + 1
    for shown in (
        "29.16",
        "0.8271",
        "1,234,567",
        "Held-out images (top) above their reconstructions.",
        "Generated (top rows) above the ground truth.",
        "no trained tokenizer in this run",
    ):
        assert shown in text, shown
    for reason in report_runs.SKIP_REASONS:
        assert reason in text, reason
    # report.md is rebuilt beside it.
    assert "![tokenizer](reconstructions.png)" in (run / "report.md").read_text()


def test_a_missing_picture_is_said_not_hidden(tmp_path):
    run = report_runs.synthetic_run(tmp_path / "run")
    (run / "gen" / "samples.png").unlink()
    page = Page(render_html(json.loads((run / "report.json").read_text()), run))
    assert "picture missing: gen/samples.png" in page.text
    assert "gen/samples.png" not in {image["data-source"] for image in page.images()}


def test_the_report_command_on_a_folder_without_a_report_is_one_line(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == 2
    captured = capsys.readouterr()
    assert captured.err == (
        f"vqtouch: error: {tmp_path}: no report.json in it; give the folder of a `vqtouch demo` run (its --out)\n"
    )
    assert main(["report", str(tmp_path / "absent")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    (tmp_path / "report.json").write_text("[1, 2]")
    assert main(["report", str(tmp_path)]) == 2
    assert "not a demo report" in capsys.readouterr().err
    assert not (tmp_path / "report.html").exists()


def test_skips_are_found_in_every_form_they_are_reported_in():
    report = {
        "stages": [
            {
                "stage": "generator",
                "status": "ran (1 s)",
                "result": {
                    "skipped": {"fd_effnetlite0": "no weights"},
                    "classifier_skipped": "no labels",
                    "by_conditioner": {"0:label": {"evaluation": "skipped: nothing held out"}},
                    "skipped_steps": 0,
                    "distribution_skipped": None,
                },
            }
        ],
        "components": [{"slot": "tokenizer.discriminator", "plugin": "patchgan", "status": "skipped: needs weights"}],
        "skipped": ["the sensor renders were not asked for"],
    }
    assert skipped_items(report) == [
        ("stage generator", "fd_effnetlite0", "no weights"),
        ("stage generator", "classifier", "no labels"),
        ("stage generator", "by_conditioner / 0:label / evaluation", "nothing held out"),
        ("component tokenizer.discriminator", "-", "needs weights"),
        ("demo", "-", "the sensor renders were not asked for"),
    ]


def test_numbers_are_shown_to_four_significant_digits():
    assert [format_value(value) for value in (29.16341, 0.000123456, 100.0, 1624977, 0.5734, True, None)] == [
        "29.16",
        "0.0001235",
        "100",
        "1,624,977",
        "0.5734",
        "true",
        "-",
    ]


def test_a_report_copied_elsewhere_keeps_its_pictures(tmp_path):
    run = report_runs.synthetic_run(tmp_path / "run")
    moved = tmp_path / "moved"
    shutil.copytree(run, moved)
    shutil.rmtree(run)
    page = Page(render_html(json.loads((moved / "report.json").read_text()), moved))
    assert set(report_runs.PICTURES) <= {image["data-source"] for image in page.images()}


class Tables(HTMLParser):
    """Every table of a page by its class: a list of rows, each a list of cells (text, class, title)."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.by_class: dict[str, list[list[tuple[str, str, str]]]] = {}
        self.paragraphs: dict[str, list[str]] = {}
        self._open: list[list[list[tuple[str, str, str]]]] = []
        self._cell: list | None = None
        self._paragraph: tuple[str, list[str]] | None = None
        self.feed(text)
        self.close()

    def handle_starttag(self, tag, attrs):
        attributes = {name: value or "" for name, value in attrs}
        if tag == "table":
            self._open.append(self.by_class.setdefault(attributes.get("class", ""), []))
        elif tag == "tr" and self._open:
            self._open[-1].append([])
        elif tag in ("td", "th") and self._open:
            self._cell = [[], attributes.get("class", ""), attributes.get("title", "")]
        elif tag == "p":
            self._paragraph = (attributes.get("class", ""), [])

    def handle_endtag(self, tag):
        if tag == "table" and self._open:
            self._open.pop()
        elif tag in ("td", "th") and self._cell is not None and self._open:
            text, css_class, title = self._cell
            self._open[-1][-1].append((" ".join("".join(text).split()), css_class, title))
            self._cell = None
        elif tag == "p" and self._paragraph is not None:
            css_class, text = self._paragraph
            self.paragraphs.setdefault(css_class, []).append(" ".join("".join(text).split()))
            self._paragraph = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell[0].append(data)
        if self._paragraph is not None:
            self._paragraph[1].append(data)

    def texts(self, css_class: str) -> list[list[str]]:
        """The cells' text of the first table of class ``css_class``, row by row."""
        return [[text for text, _, _ in row] for row in self.by_class[css_class]]


#: A generator's scores as a stage reports them (comparison keys before and after their score, in no
#: particular order) and the facts beside them.
GENERATOR_RESULT = {
    "steps": 10,
    "ceiling_psnr": 29.34,
    "psnr": 24.2953,
    "background_psnr": 32.52,
    "sampler": "posterior",
    "contact_mae": 0.05838,
    "background_contact_mae": 0.04048,
    "ceiling_contact_mae": 0.03671,
    "lpips": 0.21,
    "background_lpips": 0.5,
    "retrieval_lpips": 0.3,
    "contact_psnr": 27.5,
    "background_contact_psnr": 25.5256,
    "ssim": 0.9,
    "class_mean_ssim": 0.92,
    "background_ssim": 0.9,
    "contact_fraction": 0.2744,
    "samples": 8,
    "codebook_usage": 0.332,
    "background_fid": 12.0,
    "picture": "samples.png",
    "caption": "Generated above the ground truth.",
}


def _stage_page(result: dict) -> Tables:
    report = {"scene": "label-to-touch", "stages": [{"stage": "generator", "status": "ran (1 s)", "result": result}]}
    return Tables(render_html(report, Path("/nonexistent-run")))


def test_scores_are_one_table_with_a_row_per_score_and_a_column_per_comparison():
    table = score_table(GENERATOR_RESULT)
    # The documented order, not the result's (ceiling_ first) nor the alphabet's (class_mean_ before retrieval_).
    assert table.columns == ("background_", "ceiling_", "retrieval_", "class_mean_")
    assert list(COMPARISON_PREFIXES)[:4] == ["background_", "ceiling_", "retrieval_", "class_mean_"]
    assert table.rows["psnr"] == {"": 24.2953, "background_": 32.52, "ceiling_": 29.34}
    page = _stage_page(GENERATOR_RESULT)
    assert page.texts("scores comparison") == [
        ["score", "model", "background", "ceiling", "retrieval", "class_mean"],
        ["psnr ↑", "24.3", "32.52", "29.34", "-", "-"],
        ["contact_mae ↓", "0.05838", "0.04048", "0.03671", "-", "-"],
        ["lpips ↓", "0.21", "0.5", "-", "0.3", "-"],
        ["contact_psnr ↑", "27.5", "25.53", "-", "-", "-"],
        ["ssim ↑", "0.9", "0.9", "-", "-", "0.92"],
    ]
    # Each comparison column says what it is.
    header = page.by_class["scores comparison"][0]
    assert [title for _, _, title in header[2:]] == [COMPARISON_PREFIXES[prefix] for prefix in table.columns]


def test_keys_without_a_comparison_are_other_facts():
    facts = score_table(GENERATOR_RESULT).facts
    # background_fid has no fid beside it; the pictures are not facts.
    assert list(facts) == ["steps", "sampler", "contact_fraction", "samples", "codebook_usage", "background_fid"]
    assert _stage_page(GENERATOR_RESULT).texts("scores facts") == [
        ["other facts", "value"],
        ["steps", "10"],
        ["sampler", "posterior"],
        ["contact_fraction", "0.2744"],
        ["samples", "8"],
        ["codebook_usage", "0.332"],
        ["background_fid", "12"],
    ]
    # A result with no comparison at all has no comparison table, only its facts.
    plain = _stage_page({"steps": 40, "psnr": 29.16})
    assert "scores comparison" not in plain.by_class and plain.texts("scores facts")[1:] == [
        ["steps", "40"],
        ["psnr", "29.16"],
    ]


def test_a_model_score_is_green_only_where_it_beats_the_background_in_the_scores_direction():
    for score in (
        "mae",
        "contact_mae",
        "lpips",
        "fid",
        "kid",
        "fd_effnetlite0",
        "kid_effnetlite0",
        "pixel_mae",
        "val_loss",
    ):
        assert lower_is_better(score), score
    for score in ("psnr", "ssim", "contact_psnr", "classifier_accuracy", "codebook_usage"):
        assert not lower_is_better(score), score
    rows = _stage_page(GENERATOR_RESULT).by_class["scores comparison"][1:]
    model_cells = {row[0][0].split()[0]: row[1] for row in rows}
    # psnr: lower than the background's; contact_mae: higher (worse) than the background's, lower is better;
    # lpips: lower, lower is better; contact_psnr: higher; ssim: a tie, which is no better.
    expected = {"psnr": "worse", "contact_mae": "worse", "lpips": "better", "contact_psnr": "better", "ssim": "worse"}
    for score, verdict in expected.items():
        _, css_class, title = model_cells[score]
        assert css_class.split() == ["num", verdict], score
        assert title.startswith(f"{verdict} than the no-contact background"), (score, title)
    # Only the model's cell is coloured: the comparisons are plain numbers.
    assert all("better" not in cell[1] and "worse" not in cell[1] for row in rows for cell in row[2:])


def test_the_verdict_is_on_the_contact_region_and_says_worse_when_it_is():
    better = {"contact_fraction": 0.2744, "contact_psnr": 25.9237, "background_contact_psnr": 25.2733}
    sentence = (
        "On the contact region (27% of pixels) the model is better than the no-contact background: "
        "contact PSNR 25.92 vs 25.27 dB."
    )
    assert contact_verdict(better) == (True, sentence)
    assert _stage_page(better).paragraphs["verdict better"] == [sentence]

    worse = {"contact_psnr": 21.8278, "background_contact_psnr": 25.5256, "psnr": 24.3, "background_psnr": 32.5}
    sentence = (
        "On the contact region the model is worse than the no-contact background: contact PSNR 21.83 vs 25.53 dB."
    )
    assert contact_verdict(worse) == (False, sentence)
    assert _stage_page(worse).paragraphs["verdict worse"] == [sentence]

    tie = {"contact_psnr": 25.0, "background_contact_psnr": 25.0}
    assert contact_verdict(tie)[0] is False and "no better than" in contact_verdict(tie)[1]
    # Without a contact-region score there is no verdict: a whole-image score is no ground for one.
    whole_image_only = {"psnr": 30.0, "background_psnr": 20.0}
    assert contact_verdict(whole_image_only) is None
    assert not any(name.startswith("verdict") for name in _stage_page(whole_image_only).paragraphs)
    # Only the mean absolute error on the contact region: lower is better.
    assert contact_verdict({"contact_mae": 0.05, "background_contact_mae": 0.04})[0] is False


def test_report_md_has_the_same_comparison_table_and_verdict():
    report = {
        "scene": "label-to-touch",
        "run_dir": "/runs/x",
        "components": [],
        "stages": [{"stage": "generator", "status": "ran (1 s)", "result": GENERATOR_RESULT}],
    }
    text = render_report(report)
    table = (
        "| score | model | background | ceiling | retrieval | class_mean |\n|---|---|---|---|---|---|\n"
        "| psnr ↑ | 24.3 ✗ | 32.52 | 29.34 | - | - |\n"
        "| contact_mae ↓ | 0.05838 ✗ | 0.04048 | 0.03671 | - | - |\n"
        "| lpips ↓ | 0.21 ✓ | 0.5 | - | 0.3 | - |\n"
        "| contact_psnr ↑ | 27.5 ✓ | 25.53 | - | - | - |\n"
        "| ssim ↑ | 0.9 ✗ | 0.9 | - | - | 0.92 |\n"
    )
    assert table in text
    assert "✗ it is worse than the background (a tie counts as worse)" in text
    assert (
        "On the contact region (27% of pixels) the model is better than the no-contact background: "
        "contact PSNR 27.50 vs 25.53 dB."
    ) in text
    assert (
        "steps 10, sampler posterior, contact_fraction 0.2744, samples 8, codebook_usage 0.332, background_fid 12"
    ) in text
    # No comparison, no table: the score is a fact.
    alone = render_report({**report, "stages": [{"stage": "s", "status": "ran", "result": {"lpips": 0.2}}]})
    assert "| score |" not in alone and "lpips 0.2" in alone


def test_a_reason_skipped_by_several_stages_and_parts_is_listed_once_and_each_part_is_shown():
    """A metric without its weights is skipped by every stage that scores: one Skipped row names them all;
    a stage's parts (one per condition) each get their own scores table and picture caption."""
    reason = "metric 'lpips' needs vgg16-397923af.pth"
    part = {"psnr": 24.0, "background_psnr": 25.0, "skipped": {"lpips": reason}, "caption": "from label grid"}
    report = {
        "scene": "tour",
        "stages": [
            {"stage": "tokenizer", "status": "ran (1 s)", "result": {"psnr": 30.0, "skipped": {"lpips": reason}}},
            {
                "stage": "generator",
                "status": "ran (1 s)",
                "result": {"step": 60, "parts": {"from label": part, "from text": dict(part, psnr=26.0)}},
            },
        ],
    }
    page = render_html(report, Path("/nonexistent-run"))
    assert page.count(html.escape(reason)) == 1 and "Skipped (1)" in page
    assert "stage tokenizer, stage generator" in page
    assert "<h3>from label</h3>" in page and "<h3>from text</h3>" in page
    markdown = render_report(report | {"components": [], "run_dir": "/nonexistent-run"})
    assert "#### from label" in markdown and "#### from text" in markdown
