"""The Precision panel in a real browser (Debian's chromium driven by Playwright): the
method's Table 1 for the console's rig and its curves drawn by uPlot. Fixtures ``console``
and ``browser`` are in conftest.py."""

from __future__ import annotations

import pytest

from tests.browser_support import needs_chromium, wait_on_page
from trifuse.app.sources.sim.head import default_rig
from trifuse.app.workflows.report_format import limit_distance_cell
from trifuse.fusion.precision import analyze_precision

pytestmark = [needs_chromium, pytest.mark.slow]


def test_precision_panel_shows_table_1_and_its_curves(console, browser) -> None:
    page = browser.new_page(viewport={"width": 800, "height": 900})
    page.goto(console.signin("/console/"))
    page.wait_for_function("() => !document.body.innerText.includes('Connecting...')")
    page.get_by_text("Precision", exact=True).first.click()  # folded by default
    page.wait_for_function("() => document.body.innerText.includes('TOF pixel (')")
    text = page.evaluate("() => document.body.innerText")
    assert "principal point" in text and "region 3 edge" in text
    # the console fuses with the simulated head's rig: its numbers, as `trifuse analyze`
    ref = analyze_precision(default_rig())
    key = next(iter(ref.distance_error))
    row = [limit_distance_cell(r.x_m, 10.0) for r in ref.distance_error[key].values()]
    lines = [" ".join(t.split()) for t in text.splitlines()]
    assert any(line.startswith("41 mm") and " ".join(row) in line for line in lines), row
    # two uPlot charts (|dx| and |dy|) with their canvases, drawn at a usable size. A chart
    # is made 0 px wide and takes its container's width once the browser has measured it
    # (Viser's useElementSize): CI caught one at [0, 260], so the test waits for the width.
    sizes_js = (
        "() => [...document.querySelectorAll('.uplot canvas')].map(c =>"
        " { const r = c.getBoundingClientRect(); return [r.width, r.height]; })"
    )
    last: list = []

    def laid_out() -> bool:
        last[:] = page.evaluate(sizes_js)
        return len(last) >= 2 and all(w > 150 and h > 100 for w, h in last)

    wait_on_page(page, laid_out, lambda: f"two charts of usable size (canvases: {last})", 60.0)
    text = page.evaluate("() => document.body.innerText")
    assert "threshold 0.5 px" in text and "col L 41 mm" in text  # the legend
    # the curves are drawn: pixels of the colour cameras' orange (col R) on the canvas
    orange_js = """() => { const c = document.querySelector('.uplot canvas');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4)
          if (d[i] > 200 && d[i + 1] > 90 && d[i + 1] < 160 && d[i + 2] < 60 && d[i + 3] > 200) n++;
        return n; }"""
    # drawn once its new width is committed (uPlot redraws on the next animation frame)
    counted: list[int] = [0]

    def drawn() -> bool:
        counted[0] = page.evaluate(orange_js)
        return counted[0] > 50

    wait_on_page(page, drawn, lambda: f"the orange curve drawn ({counted[0]} px)", 30.0)
    page.close()
