"""Outside text in Viser's markdown (issue 29, app/server/markdown_text.py): Viser reads
``![x](PATH)`` as a file on the server and sends it to every browser; every file name,
sensor name, path and error message the panels show is escaped, so it reads literally and
makes no image, link, autolink or HTML."""

from __future__ import annotations

import base64
import dataclasses
import html
import re
from html.parser import HTMLParser
from pathlib import Path
from types import SimpleNamespace

import imageio.v3 as iio
import numpy as np
import pytest
import viser
import viser._gui_handles as viser_handles
from markdown_it import MarkdownIt

from tests.browser_support import needs_chromium
from trifuse.app.recording.recorder import RecordingState
from trifuse.app.server.markdown_text import MAX_CHARS, WORD_JOINER, md_text
from trifuse.app.server.panels.calibration import CalibrationPanel, views_html
from trifuse.app.server.panels.display import balance_text
from trifuse.app.server.panels.precision import compute, table_markdown
from trifuse.app.server.panels.rig_files import RigFilesPanel, zip_files
from trifuse.app.server.panels.scene3d import rig_difference_markdown
from trifuse.app.server.panels.source import health_text, recording_text
from trifuse.app.server.routers.viser_bridge import VISER_IMAGE_READER, start_guarded_viser
from trifuse.app.server.runtime.sensor_health import SensorHealth
from trifuse.app.server.runtime.thermal_balance import BalanceStatus
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.workflows.calib_session import ViewInfo
from trifuse.calib.rig import Eye, Rig
from trifuse.calib.rig_formats import export_rig

NASTY = [
    "![x](/etc/hostname)",
    "![x](../../../../etc/passwd)",
    "![![x](a.png)](b.png)",
    "!\n[x](y.png)",
    "\\![x](y.png)",
    "[click](javascript:alert(1))",
    "[click](http://evil.example 'title')",
    "[ref]: /etc/hostname",
    "![x][ref] and [x][] and [ref]",
    "[^1] footnote",
    "<http://evil.example>",
    "<ops@evil.example>",
    "<img src=x onerror=alert(1)>",
    "<script>alert(1)</script>",
    '<a href="http://evil.example">x</a>',
    "<!-- hidden -->",
    "www.evil.example and WWW.EVIL.EXAMPLE/x",
    "https://evil.example/x ftp://evil.example",
    "ops@evil.example mailto:ops@evil.example xmpp:ops@evil.example",
    "&lt;img src=x&gt; &#60;b&#62; &amp;",
    "`code` ``more``",
    "**bold** __bold__ *it* _it_ ~~gone~~ ~gone~",
    "# heading",
    "- item",
    "+ item",
    "1. item",
    "2) item",
    "> quote",
    "| a | b |",
    "---",
    "===",
    "~~~",
    "    indented code",
    "trailing backslash\\",
    "line\nbreak\r\nand\ttab and \x00 nul and \x85 next line",
    "ccd_left rig-0001 short.mcap x_y_z 1.5 (7) a: b",
    "' \" ; % $ ^ { } ( ) / ,",
    "℮ ！［x］（y.png） ‹img›",
]
"""Names, messages and paths an attacker (or an unlucky file) could bring."""

SECRET_RGB = (201, 17, 99)


def literal(text: str) -> str:
    """What the operator should read: the text with control characters as spaces."""
    return "".join(" " if ord(c) < 0x20 or 0x7F <= ord(c) < 0xA0 else c for c in text).strip()


def seen(text: str) -> str:
    """Rendered text as the operator reads it: word joiners are invisible."""
    return text.replace(WORD_JOINER, "")


GFM_BARE_LINKS = re.compile(
    r"(?i)(https?://|www(?=\.))[-.\w]+|[-.\w+]+@[-\w]+(\.[-\w]+)+", re.ASCII
)
"""remark-gfm's patterns for bare links (mdast-util-gfm-autolink-literal), which it
applies to the text after escapes are resolved."""


def problems(md: str) -> list[str]:
    """Everything in ``md`` that is more than text and formatting: images, links, raw HTML
    (markdown-it, CommonMark with GFM tables and strikethrough, as Viser's client), GFM's
    bare links in the resolved text, and Viser's server-side image pattern."""
    parser = MarkdownIt("commonmark").enable(["table", "strikethrough"])
    found, tokens = [], parser.parse(md)
    while tokens:
        t = tokens.pop()
        if t.type in ("image", "link_open", "html_inline", "html_block"):
            found.append(f"{t.type} {t.content or t.attrs}")
        tokens += t.children or []
    for text in rendered_text(md):
        found += [f"bare link {m.group()!r}" for m in GFM_BARE_LINKS.finditer(text)]
    if "![" in md or viser_handles._parse_markdown(md, None) != md:
        found.append("Viser's image pattern")
    return found


class TagNames(HTMLParser):
    """The names of the elements in some HTML."""

    def __init__(self) -> None:
        super().__init__()
        self.names: set[str] = set()

    def handle_starttag(self, tag: str, attrs: list) -> None:
        self.names.add(tag)


def rendered_text(md: str) -> list[str]:
    """The text of every inline run (paragraph, heading, table cell) as markdown-it reads
    it, formatting marks dropped."""
    parser = MarkdownIt("commonmark").enable(["table", "strikethrough"])
    return [
        "".join(c.content for c in t.children or [] if c.type in ("text", "code_inline"))
        for t in parser.parse(md)
        if t.type == "inline"
    ]


@pytest.fixture(scope="module")
def server():
    s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield s
    s.stop()


@pytest.fixture
def secret_png(tmp_path) -> Path:
    path = tmp_path / "secret.png"
    iio.imwrite(path, np.full((4, 4, 3), SECRET_RGB, np.uint8))
    return path


@pytest.fixture
def image_reads(monkeypatch) -> list[str]:
    """Every path Viser's markdown tries to read as an image (its behaviour unchanged)."""
    reads: list[str] = []
    original = VISER_IMAGE_READER  # Viser's own, even after a console turned it off

    def spy(url, image_root):
        reads.append(url)
        return original(url, image_root)

    monkeypatch.setattr(viser_handles, "_get_data_url", spy)
    return reads


def test_viser_reads_an_image_path_in_markdown_on_the_server(server, secret_png, image_reads):
    """The attack's premise, on Viser itself: markdown naming a file on the server sends
    that file's pixels to every browser as a data URL."""
    with pytest.warns(UserWarning, match="image_root"):
        md = server.gui.add_markdown(f"![x]({secret_png})")
    assert image_reads == [str(secret_png)]
    encoded = md._markdown.split("base64,")[1].rstrip(")")
    assert md._markdown.startswith("![x](data:image/png;base64,")
    png = iio.imread(base64.b64decode(encoded))
    assert tuple(png[0, 0, :3]) == SECRET_RGB  # the file's own pixels
    md.remove()


def test_the_consoles_viser_reads_no_file_even_for_unescaped_markdown(secret_png, monkeypatch):
    """Defence in depth: in a process running the console's Viser, markdown that names a
    file (as a panel that forgot to escape would pass it) is sent as it is, unread."""
    monkeypatch.setattr(viser_handles, "_get_data_url", VISER_IMAGE_READER)
    server, _ = start_guarded_viser()
    try:
        md = server.gui.add_markdown(f"![x]({secret_png}) ![y](/etc/hostname)")
        assert md._markdown == f"![x]({secret_png}) ![y](/etc/hostname)"
    finally:
        server.stop()


@pytest.mark.parametrize("target", ["{png}", "/etc/hostname"])
def test_an_upload_named_as_an_image_reads_no_file(server, secret_png, image_reads, target):
    """The issue's attack: a rig upload named ``![x](PATH)`` is refused and its name shown
    in the panel, and Viser read PATH (the PNG went to every browser; /etc/hostname made
    Viser's image reader raise out of the panel's handler). Now the name is shown as text
    and nothing is read."""
    ctx = SimpleNamespace(
        server=server,
        pipeline=SimpleNamespace(rig=default_rig()),
        save_rig=lambda rig, report: SimpleNamespace(name="rig-0001"),
    )
    panel = RigFilesPanel(ctx)  # type: ignore[arg-type]
    name = "![x](" + target.format(png=secret_png) + ")"
    panel.upload_rig(SimpleNamespace(name=name, content=b"\xff\xfe"))
    md = panel.message.content
    assert image_reads == [] and "data:" not in panel.message._markdown
    assert panel.message._markdown == md and problems(md) == []
    assert [seen(t) for t in rendered_text(md)] == [
        f"Not done: UploadError: {name}: not a text file or a zip"
    ]


@pytest.mark.parametrize("nasty", NASTY)
def test_escaped_text_reads_literally_and_does_nothing(nasty) -> None:
    md = md_text(nasty)
    assert problems(md) == []
    assert seen("".join(rendered_text(md))) == literal(nasty)
    for template in ("**Not done:** {}", "| {} | 1 |\n|---|---|\n| {} | 2 |", "- {}", "x {} y"):
        assert problems(template.replace("{}", md)) == [], template
    assert md_text("x" * (MAX_CHARS + 5)) == "x" * MAX_CHARS + "…"


def renamed(rig: Rig, nasty: str) -> Rig:
    """``rig`` with every sensor's name prefixed by ``nasty`` (as an imported rig may
    name them: the formats' importers take any name)."""
    new = {n: f"{nasty} {n}" for n in rig.sensors}
    return Rig(
        {new[n]: dataclasses.replace(s, name=new[n]) for n, s in rig.sensors.items()},
        new[rig.reference],
        {e: Eye(new[v.color], new[v.thermal]) for e, v in rig.eyes.items()},
    )


def panel_texts(server, nasty: str) -> list[tuple[str, bool]]:
    """Markdown the panels make from outside text that is ``nasty``, and whether it shows
    ``nasty`` itself (not only something made from it)."""
    rig = default_rig()
    bad_rig = renamed(rig, nasty)
    texts = []
    # Rig files: an upload's name and the importer's refusal of the files' sensor names
    # (it echoes them), and the name in a success
    ctx = SimpleNamespace(
        server=server,
        pipeline=SimpleNamespace(rig=rig),
        save_rig=lambda r, report: SimpleNamespace(name=nasty),
    )
    panel = RigFilesPanel(ctx)  # type: ignore[arg-type]
    for content, outcome, shows_nasty in (
        (b"\xff", "**Not done:** UploadError", True),
        (zip_files(export_rig(bad_rig, "ros").files), "**Not done:** RigError", False),
        (zip_files(export_rig(rig, "ros").files), "Imported", True),
    ):
        upload = SimpleNamespace(name=nasty, content=content)
        panel.upload_rig(upload)
        assert panel.message.content.startswith(outcome), panel.message.content
        texts.append((panel.message.content, shows_nasty))
    # sensor names in the Precision table and the 3D scene's rig comparison
    no_eyes = Rig(bad_rig.sensors, bad_rig.reference)
    texts.append((table_markdown(compute(no_eyes)), True))
    texts.append((rig_difference_markdown(nasty, bad_rig, rig), True))
    # recordings, sensor health, the thermal balance
    texts.append((recording_text(RecordingState(True, True, path=nasty, error=nasty)), True))
    texts.append((recording_text(RecordingState(True, files=[nasty, nasty], error=nasty)), True))
    texts.append((recording_text(RecordingState(False, error=nasty)), True))
    texts.append((health_text({nasty: SensorHealth(nasty, "failing", reason=nasty)}), True))
    pipeline = SimpleNamespace(
        radiometry={nasty: SimpleNamespace(balance_offset_k=0.5, balance_gain=1.0)}
    )
    texts.append((balance_text(BalanceStatus(waiting=nasty), False, pipeline), True))  # type: ignore[arg-type]
    # the calibration's results (sensor names, polarity, reasons, notes)
    sensor = SimpleNamespace(sigma={}, views_used=3, views_detected=4, rms_px=0.2)
    polarity = {"polarity": "black squares hot", "decided_by": "data", "anchor": nasty}
    result = SimpleNamespace(
        rms_px=0.2,
        reference=nasty,
        sensors={nasty: sensor},
        intrinsics_only={nasty: SimpleNamespace(**vars(sensor), pose_unknown=nasty)},
        polarity={nasty: SimpleNamespace(as_dict=lambda: polarity)},
        excluded_sensors={nasty: nasty},
        notes=[nasty],
        verdict=None,
    )
    fake_panel = SimpleNamespace(ctx=SimpleNamespace(ground_truth_rig=None))
    texts.append((CalibrationPanel._results_md(fake_panel, result), True))  # type: ignore[arg-type]
    # the cross-validation's lines (an eye's name and why it was skipped)
    cv = {"skipped": None, "views": {"A": [nasty]}, "eyes": {nasty: {"skipped": nasty}}}
    report = {"cross_validation": cv}
    texts.append((CalibrationPanel._results_md(fake_panel, result, report), True))  # type: ignore[arg-type]
    return texts


@pytest.mark.filterwarnings("ignore:Duplicate name")  # zip_files of NUL-cut sensor names
@pytest.mark.parametrize("nasty", NASTY)
def test_panels_show_outside_text_literally(server, image_reads, nasty) -> None:
    """Every panel text built from ``nasty`` (as a file name, sensor name, path, reason,
    error) has no image, link or HTML in it, Viser reads no file for it, and the operator
    reads ``nasty`` as it is."""
    for md, shows_nasty in panel_texts(server, nasty):
        assert problems(md) == [], md
        shown = seen(" ".join(rendered_text(md)))
        assert literal(nasty) in shown or not shows_nasty, (md, shown)
    assert image_reads == []
    # the Calibration panel's view table is HTML: the view's name is escaped as HTML
    tags = TagNames()
    tags.feed(views_html([ViewInfo(nasty, ["tof"])], ["tof"]))
    assert tags.names <= {"p", "div", "table", "tr", "th", "td", "br"}
    assert html.escape(nasty) in views_html([ViewInfo(nasty, ["tof"])], ["tof"])


@needs_chromium
@pytest.mark.slow
def test_viser_client_renders_escaped_text_as_text(browser) -> None:
    """Viser's own client (react-markdown, remark-gfm, raw HTML on) in Chromium: a control
    with a real link, bare link and HTML element renders them, and every escaped string
    renders as one paragraph of plain text reading as the string does."""
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        server.gui.add_markdown("CONTROL [link](http://a.invalid) www.b.invalid <b id=ctl>x</b>")
        for i, nasty in enumerate(NASTY):
            server.gui.add_markdown(f"NASTY{i:02d} {md_text(nasty)}")
        page = browser.new_page()
        page.goto(f"http://127.0.0.1:{server.get_port()}/")
        page.wait_for_function(f"document.body.innerText.includes('NASTY{len(NASTY) - 1:02d}')")
        control = page.evaluate(
            """() => [...document.querySelectorAll('p')]
                .filter(p => p.textContent.startsWith('CONTROL'))
                .map(p => [...p.querySelectorAll('a, b')].map(e => e.href || e.tagName))"""
        )
        assert control == [["http://a.invalid/", "http://www.b.invalid/", "B"]]
        shown = page.evaluate(
            """() => [...document.querySelectorAll('p')]
                .filter(p => /^NASTY\\d\\d /.test(p.textContent))
                .map(p => [p.textContent, p.querySelectorAll('*').length])"""
        )
        page.close()
    finally:
        server.stop()
    assert len(shown) == len(NASTY)
    for (text, elements), nasty in zip(sorted(shown), NASTY, strict=True):
        assert elements == 0, (nasty, text)  # no link, image, emphasis or HTML inside
        assert " ".join(seen(text[8:]).split()) == " ".join(literal(nasty).split())
