"""The reports as a browser shows them: headless Chromium, where it is installed.

:func:`rendered_images` opens a copy of a report with a small script added that, once the page
has loaded, writes every image's natural and displayed size into the page; Chromium's
``--dump-dom`` prints the page after that, and a screenshot of the same window is kept beside
it. :func:`check_rendered_images` holds what the report promises a reader (docs/ARCHITECTURE.md §5,
"Report"): no image stretched, every map at equal aspect, and the smallest text of every figure
at least :data:`MIN_READABLE_PX` pixels high at the size the page shows it.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
from pathlib import Path

from georefine.evaluation.figures import AXES_KEY, MIN_FONT_KEY

MIN_READABLE_PX = 9.0
"""Smallest text height (CSS px at 100 % zoom) counted as readable: 7 pt, the size of footnotes."""

WINDOW = (1280, 1000)
"""A laptop's browser window."""

_PROBE = """<script>
window.addEventListener("load", () => {
  const out = Array.from(document.images).map((im) => ({
    alt: im.alt, natural: [im.naturalWidth, im.naturalHeight], shown: [im.clientWidth, im.clientHeight],
    src: im.src.slice(0, 64)}));
  const pre = document.createElement("pre");
  pre.id = "georefine-probe";
  pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script>"""


def png_facts(data: bytes) -> dict[str, str]:
    """The text chunks of a PNG (what :func:`georefine.evaluation.figures.save_png` wrote, among
    others), read by Pillow, matplotlib's own image library."""
    import io

    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(data)) as im:
            if im.format != "PNG":
                raise ValueError(f"not a PNG: {im.format}")
            return dict(im.text)
    except UnidentifiedImageError:
        raise ValueError("not a PNG") from None


def chromium() -> str | None:
    """The Chromium (or Chrome) executable on the PATH, or None."""
    return next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)


def _run(browser: str, args: list[str], timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                           f"--window-size={WINDOW[0]},{WINDOW[1]}", *args], capture_output=True, text=True,
                          timeout=timeout)


def rendered_images(report: Path, work: Path) -> tuple[list[dict], Path]:
    """Every ``<img>`` of ``report`` as Chromium lays it out (``alt``, ``natural`` and ``shown``
    ``[width, height]`` in px, the facts :func:`georefine.evaluation.figures.save_png` wrote into its
    PNG under ``facts``) and a screenshot of the page's first window."""
    browser = chromium()
    assert browser is not None
    page = report.read_text(encoding="utf-8")
    images = re.findall(r'<img alt="([^"]*)" src="data:image/png;base64,([^"]+)"', page)
    probe = work / f"probe-{report.name}"
    probe.write_text(page.replace("</body>", _PROBE + "</body>"), encoding="utf-8")
    proc = _run(browser, ["--virtual-time-budget=20000", "--dump-dom", probe.as_uri()])
    found = re.search(r'<pre id="georefine-probe">(.*?)</pre>', proc.stdout, re.S)
    assert found is not None, proc.stderr[-2000:]
    import html

    shown = json.loads(html.unescape(found.group(1)))
    assert len(shown) == len(images), (len(shown), len(images))
    for item, (_, data) in zip(shown, images):
        item["facts"] = png_facts(base64.b64decode(data))
    shot = work / f"{report.stem}.png"
    proc = _run(browser, [f"--screenshot={shot}", report.as_uri()])
    assert shot.is_file(), proc.stderr[-2000:]
    return shown, shot


def check_rendered_images(shown: list[dict], maps: tuple[str, ...], pictures: tuple[str, ...] = ()) -> None:
    """No image stretched; the figures whose ``alt`` contains one of ``maps`` with every axes at
    equal aspect; every figure's smallest text readable as shown (module docstring). Images whose
    ``alt`` contains one of ``pictures`` are pictures, not plots (matches drawn on a photo): only
    their proportions are checked."""
    assert shown, "no image in the report"
    for im in shown:
        (nw, nh), (sw, sh) = im["natural"], im["shown"]
        assert nw > 0 and sw > 0, im
        assert abs(sw / nw - sh / nh) <= 0.02 * sw / nw, f"{im['alt']}: drawn {sw}x{sh} of {nw}x{nh}"
        if any(p in im["alt"] for p in pictures):
            continue
        facts = im["facts"]
        assert MIN_FONT_KEY in facts and AXES_KEY in facts, f"{im['alt']}: a figure not saved by save_png"
        if facts[MIN_FONT_KEY]:
            px = float(facts[MIN_FONT_KEY]) * sw / nw
            assert px >= MIN_READABLE_PX, f"{im['alt']}: smallest text {px:.1f} px high as shown"
        if any(m in im["alt"] for m in maps):
            equal, total = map(int, facts[AXES_KEY].split("/"))
            assert total > 0 and equal == total, f"{im['alt']}: {facts[AXES_KEY]} axes at equal aspect"
